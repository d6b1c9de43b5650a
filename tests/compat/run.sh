#!/usr/bin/env bash
# Old server against new, answer for answer: after a refactor that must not
# change behaviour, start an older build's blapose-server and this tree's
# side by side with the same flags, send both the same requests with this
# tree's blapose-client (every example: streamed, with the camera, lifted by
# the server, with a stature, offline with each model, the exports, bad
# requests), and compare every file written and every error printed byte for
# byte. Not run by CI: it needs a second build of an older commit, e.g.
#   git worktree add --detach ../old b35603e
#   (cd ../old && cargo build --release -p blapose-server)
#   tests/compat/run.sh ../old/target/release/blapose-server [OUT_DIR]
# Options only the new server has (the motion stage) are not sent: an older
# server does not know them.
set -euo pipefail
cd "$(dirname "$0")/../.."
. tests/e2e-lib.sh

OLD=${1:?usage: tests/compat/run.sh OLD_BLAPOSE_SERVER [OUT_DIR]}
[ -x "$OLD" ] || { echo "error: $OLD is not an executable" >&2; exit 2; }
build_release -p blapose-server -p blapose-client
use_out_dir "${2:-}"
CLIENT=target/release/blapose-client
KEY=hex:00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff
FLAGS=(--session-key "$KEY" --lifter-weights models/lifter_videopose27_causal.safetensors)

# transcript NAME: every request against $URL, files and messages in $OUT/NAME.
transcript() {
    local dir=$OUT/$1 ex name
    mkdir -p "$dir"
    run() {  # run LABEL ARGS...: what the client printed (less session ids,
        # timings and output paths) and its exit status kept
        local label=$1 rc
        shift
        set +e
        "$CLIENT" --server "$URL" "$@" >"$dir/$label.out" 2>&1
        rc=$?
        set -e
        grep -v -e '^session ' -e 'frames/s' -e '^wrote ' "$dir/$label.out" >"$dir/$label.txt" || true
        rm "$dir/$label.out"
        echo "exit $rc" >>"$dir/$label.txt"
    }
    for ex in examples/*.npz; do
        name=$(basename "$ex" .npz)
        run "$name.replay" replay "$ex" --out "$dir/$name.replay.npz" --json "$dir/$name.replay.json"
        run "$name.camera" replay "$ex" --camera --out "$dir/$name.camera.npz" --json "$dir/$name.camera.json"
        run "$name.lifted" replay "$ex" --server-lifter --out "$dir/$name.lifted.npz"
        run "$name.height" replay "$ex" --height 1.62 --sex female --out "$dir/$name.height.npz"
        run "$name.window1" replay "$ex" --window 1 --out "$dir/$name.window1.npz"
        run "$name.bigru" adjust "$ex" --out "$dir/$name.bigru.npz" --json "$dir/$name.bigru.json" \
            --bvh "$dir/$name.bvh" --c3d "$dir/$name.c3d" --trc "$dir/$name.trc"
        run "$name.gru" adjust "$ex" --model gru --out "$dir/$name.gru.npz"
        run "$name.adjust_camera" adjust "$ex" --camera --out "$dir/$name.adjust_camera.npz"
    done
}

BLAPOSE_SERVER_BIN=target/release/blapose-server start_server "$OUT/new.log" "${FLAGS[@]}"
transcript new
kill "$SERVER_PID"
wait "$SERVER_PID" 2>/dev/null || true
SERVER_PID=
BLAPOSE_SERVER_BIN=$OLD start_server "$OUT/old.log" "${FLAGS[@]}"
transcript old

files=$(find "$OUT/new" -type f | wc -l)
if diff -r "$OUT/old" "$OUT/new" >"$OUT/diff.txt"; then
    echo "compat: $files files and messages identical (old $OLD, new $(git rev-parse --short HEAD))"
else
    echo "compat: old and new differ ($(grep -c '^\(Only\|Binary\|diff\)' "$OUT/diff.txt") files):" >&2
    head -n 40 "$OUT/diff.txt" >&2
    exit 1
fi
