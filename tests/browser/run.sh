#!/usr/bin/env bash
# Browser test of the HTML replay report, in real headless Chromium.
#
# Writes one report with the release client (`blapose-client replay --html`)
# and one with Python (`blapose.write_replay_html`), both from an example
# replayed through a release server on a free loopback port (embedded
# weights), and checks both pages with check_report.mjs (no errors, no
# network, a drawn 3D view, animation, slider and play/pause).
#
# Needs: Debian's chromium at /usr/bin/chromium (installed here when
# missing; needs root), node + npm (playwright-core from package-lock.json,
# no browser download), the release binaries (built here when stale) and a
# Python with the blapose package: $BLAPOSE_PYTHON, default the venv that
# .ci/run creates (target/pyvenv-ci). $BLAPOSE_REPORT_DIR keeps the reports
# and a screenshot (default: a temporary directory, removed).
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
PY=${BLAPOSE_PYTHON:-$ROOT/target/pyvenv-ci/bin/python}
EXAMPLE=${BLAPOSE_REPORT_EXAMPLE:-examples/cmu_02_02_walk.npz}

if [ ! -x /usr/bin/chromium ] && [ -z "${CHROMIUM:-}" ]; then
    echo "== installing Debian's chromium"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null
fi
if [ ! -x "$PY" ]; then
    echo "error: $PY not found: run .ci/run, or set BLAPOSE_PYTHON to a Python with './python' installed" >&2
    exit 1
fi

echo "== npm ci (tests/browser)"
(cd tests/browser && npm ci --no-audit --no-fund --loglevel=error)
cargo build --release --quiet -p blapose-server -p blapose-client

if [ -n "${BLAPOSE_REPORT_DIR:-}" ]; then
    OUT=$BLAPOSE_REPORT_DIR
    mkdir -p "$OUT"
else
    OUT=$(mktemp -d)
fi
SERVER_PID=
cleanup() {
    if [ -n "$SERVER_PID" ]; then kill "$SERVER_PID" 2>/dev/null || true; wait "$SERVER_PID" 2>/dev/null || true; fi
    if [ -z "${BLAPOSE_REPORT_DIR:-}" ]; then rm -rf "$OUT"; fi
}
trap cleanup EXIT

# The server picks a free port (--addr 127.0.0.1:0) and logs it.
target/release/blapose-server --addr 127.0.0.1:0 --no-metrics >"$OUT/server.log" 2>&1 &
SERVER_PID=$!
URL=
for _ in $(seq 600); do
    PORT=$(sed -n 's/.*serving blapose\.v1 addr=127\.0\.0\.1:\([0-9]*\).*/\1/p' "$OUT/server.log" | head -n 1)
    if [ -n "$PORT" ]; then URL=http://127.0.0.1:$PORT; break; fi
    kill -0 "$SERVER_PID" 2>/dev/null || break
    sleep 0.1
done
if [ -z "$URL" ]; then
    echo "error: blapose-server did not start:" >&2
    cat "$OUT/server.log" >&2
    exit 1
fi

echo "== reports of $EXAMPLE (server $URL)"
target/release/blapose-client --server "$URL" replay "$EXAMPLE" --html "$OUT/report_rust.html" >/dev/null
"$PY" - "$URL" "$EXAMPLE" "$OUT/report_python.html" <<'PYEOF'
import sys
from pathlib import Path

import blapose

url, example, out = sys.argv[1:]
seq = blapose.load_replay(example)
with blapose.Client(url) as client:
    with client.session(layout=seq.layout, image_size=seq.image_size) as s:
        results = list(s.stream(seq.frames()))
blapose.write_replay_html(out, seq, results, title=Path(example).name, info={"model": "gru (Python session)"})
PYEOF
ls -l "$OUT"/report_*.html | awk '{print "   " $5 " bytes  " $NF}'

echo "== headless Chromium: check both reports"
node tests/browser/check_report.mjs "$OUT/report_rust.html" "$OUT/report_python.html" --screenshot "$OUT/report_rust.png"
