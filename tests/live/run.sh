#!/usr/bin/env bash
# The live page end to end in real headless Chromium: a fake camera fed from a
# real picture of a person (messi5.jpg from Debian's opencv-doc, slowly panned
# into a 640x480 30 Hz .y4m by Debian's ffmpeg; $BLAPOSE_LIVE_VIDEO takes any
# video instead, e.g. opencv-doc's vtest.avi, whose walkers are too small for
# MediaPipe to find often), MediaPipe's PoseLandmarker in the page, the release server
# lifting and adjusting over its WebSocket (--web-addr), and check_live.mjs
# reading window.blapose.stats: frames/s, latency, every frame answered, the
# lengths settled, the skeleton drawn, nothing from outside.
#
# Needs: node + npm (web/ and tests/live/ from their lock files; no browser
# download), Debian's chromium, ffmpeg and opencv-doc (installed here when
# missing; needs root). $BLAPOSE_LIVE_DIR keeps the video, the log and the
# screenshot (default: a temporary directory, removed); $BLAPOSE_LIVE_SECONDS
# how long the page runs (default 25); $BLAPOSE_LIVE_MIN_FPS and
# $BLAPOSE_LIVE_MAX_P99_MS the speed asserted (default 15 and 100).
set -euo pipefail
cd "$(dirname "$0")/../.."
# shellcheck source=../e2e-lib.sh
. tests/e2e-lib.sh
PICTURE=/usr/share/doc/opencv-doc/examples/data/messi5.jpg
SOURCE=${BLAPOSE_LIVE_VIDEO:-$PICTURE}

missing=()
[ -x /usr/bin/chromium ] || [ -n "${CHROMIUM:-}" ] || missing+=(chromium)
command -v ffmpeg >/dev/null || missing+=(ffmpeg)
[ -f "$SOURCE" ] || missing+=(opencv-doc)
if [ ${#missing[@]} -gt 0 ]; then
    echo "== installing Debian's ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

echo "== npm ci (web/: the page and its assets; tests/live)"
(cd web && npm ci --no-audit --no-fund --loglevel=error)
(cd tests/live && npm ci --no-audit --no-fund --loglevel=error)
[ -n "${BLAPOSE_SERVER_BIN:-}" ] || build_release -p blapose-server

use_out_dir "${BLAPOSE_LIVE_DIR:-}"
if [ "$SOURCE" = "$PICTURE" ]; then
    ffmpeg -loglevel error -y -loop 1 -i "$SOURCE" -t 10 -pix_fmt yuv420p \
        -vf "crop=w=iw*0.9:h=ih*0.9:x='(iw-ow)/2+20*sin(t)':y='(ih-oh)/2+10*cos(0.7*t)',scale=640:480,fps=30" \
        "$OUT/camera.y4m"
else
    ffmpeg -loglevel error -y -i "$SOURCE" -t 20 -vf "scale=640:480,fps=30" -pix_fmt yuv420p "$OUT/camera.y4m"
fi

# No lifter flag: the page relies on the server's embedded lifter.
start_server "$OUT/server.log" --web-addr 127.0.0.1:0
WEB=
for _ in $(seq 100); do
    WEB=$(sed -n 's#.*browser transport at http://\(127\.0\.0\.1:[0-9]*\)/.*#\1#p' "$OUT/server.log" | head -n 1)
    [ -n "$WEB" ] && break
    sleep 0.1
done
[ -n "$WEB" ] || { echo "error: the server did not log its web address:" >&2; cat "$OUT/server.log" >&2; exit 1; }

echo "== headless Chromium with a fake camera: http://$WEB/"
node tests/live/check_live.mjs "http://$WEB/" "$OUT/camera.y4m" "$OUT/live.png" "${BLAPOSE_LIVE_SECONDS:-25}"
