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
# shellcheck source=../e2e-lib.sh
. tests/e2e-lib.sh
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
build_release -p blapose-server -p blapose-client

use_out_dir "${BLAPOSE_REPORT_DIR:-}"

# The server picks a free port and logs it (tests/e2e-lib.sh).
start_server "$OUT/server.log"

echo "== reports of $EXAMPLE (server $URL)"
# The Rust report with the motion stage (the pelvis path card), the Python one without.
target/release/blapose-client --server "$URL" replay "$EXAMPLE" --camera --motion --html "$OUT/report_rust.html" >/dev/null
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
grep -q '"root":\[' "$OUT/report_rust.html" || { echo "error: the --motion report carries no pelvis path" >&2; exit 1; }
ls -l "$OUT"/report_*.html | awk '{print "   " $5 " bytes  " $NF}'

echo "== headless Chromium: check both reports"
node tests/browser/check_report.mjs "$OUT/report_rust.html" "$OUT/report_python.html" --screenshot "$OUT/report_rust.png"
