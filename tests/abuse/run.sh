#!/usr/bin/env bash
# The server's limits under abuse, on loopback, bounded (well under two
# minutes): each case asserts its limit, the server's memory growth (at most
# 64 MB from one connection) and a healthy client's latency (p99 within 2x
# of its baseline, at least 5 ms), with the driver bench/src/bin/abuse/:
#   streams   many streams on one HTTP/2 connection (--max-concurrent-streams)
#   sessions  one client opening sessions as fast as it can while another
#             streams (--max-sessions-per-client, clients told apart by
#             --client-header from a trusted proxy)
#   token     one session token resumed on two replicas sharing a key: one
#             live copy per replica, refused after close and after expiry
#   bomb      blapose-client on a replay file whose pose_3d is 2 GiB of
#             zeros deflated to 2 MB: refused, naming pose_3d, with the
#             client's peak RSS no more than on the valid example
#   idle      400 connections from 8 addresses that send the preface and
#             only answer PINGs: GOAWAY within --max-connection-idle + 10 s
#   flood     one connection flooding WINDOW_UPDATE frames: GOAWAY within
#             a second (--max-control-frames-per-second)
# A limit the server does not enforce fails its case with "not enforced".
# The servers run with --max-queue-delay 0: a lone stream (the baseline)
# never waits for a batch, while any concurrent stream makes it wait up to
# the batching delay (1 ms by default) by design; without the wait the
# latency check sees what the abuse costs, not the batching policy.
# Usage: tests/abuse/run.sh [OUT_DIR]   (logs kept in OUT_DIR when given)
set -euo pipefail
cd "$(dirname "$0")/../.."
. tests/e2e-lib.sh

cargo build --release -q -p blapose-server -p blapose-client -p blapose-bench --bin abuse
use_out_dir "${1:-}"
ABUSE=target/release/abuse
CLIENT=target/release/blapose-client
STREAM_LIMIT=64
SESSION_LIMIT=8
KEY=hex:00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff
failed=()

stop_server() {
    kill "$SERVER_PID" 2>/dev/null || true
    wait "$SERVER_PID" 2>/dev/null || true
    SERVER_PID=
}

run_case() {
    local name=$1
    shift
    if ! "$@"; then
        echo "FAIL: abuse case $name" >&2
        failed+=("$name")
    fi
}

start_server "$OUT/streams.log" --max-queue-delay 0 --max-concurrent-streams "$STREAM_LIMIT"
run_case streams "$ABUSE" streams --server "$URL" --server-pid "$SERVER_PID" --streams 400 --limit "$STREAM_LIMIT"
stop_server

start_server "$OUT/sessions.log" --max-queue-delay 0 --client-header x-blapose-client --trusted-proxies 127.0.0.1 \
    --max-sessions-per-client "$SESSION_LIMIT"
run_case sessions "$ABUSE" sessions --server "$URL" --server-pid "$SERVER_PID" \
    --header x-blapose-client --attempts 200 --limit "$SESSION_LIMIT"
stop_server

start_server "$OUT/connections.log" --max-queue-delay 0 --max-connection-idle 4s --max-control-frames-per-second 1000
run_case idle "$ABUSE" idle --server "$URL" --server-pid "$SERVER_PID" --connections 400 --addresses 8 --idle 4
run_case flood "$ABUSE" flood --server "$URL" --server-pid "$SERVER_PID"
stop_server

start_server "$OUT/replica_b.log" --session-key "$KEY" --token-ttl 4s
REPLICA_PID=$SERVER_PID
REPLICA_URL=$URL
start_server "$OUT/replica_a.log" --session-key "$KEY" --token-ttl 4s
run_case token "$ABUSE" token --server "$URL" --replica "$REPLICA_URL" --token-ttl 4

# The zip bomb: the client against replica A, measured by its peak RSS.
peak_rss_kb() {  # peak_rss_kb LOG CMD...: runs CMD, prints its max RSS in kB
    local log=$1
    shift
    python3 - "$log" "$@" <<'PY'
import resource, subprocess, sys
with open(sys.argv[1], "w") as log:
    rc = subprocess.run(sys.argv[2:], stdout=log, stderr=subprocess.STDOUT).returncode
print(rc, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
PY
}
bomb_case() {
    "$ABUSE" bomb --out "$OUT/bomb.npz"
    read -r rc_valid rss_valid < <(peak_rss_kb "$OUT/client_valid.log" "$CLIENT" --server "$URL" adjust examples/cmu_02_02_walk.npz)
    read -r rc_bomb rss_bomb < <(peak_rss_kb "$OUT/client_bomb.log" "$CLIENT" --server "$URL" adjust "$OUT/bomb.npz")
    echo "  client peak RSS: valid example $((rss_valid / 1024)) MB (exit $rc_valid), bomb $((rss_bomb / 1024)) MB (exit $rc_bomb): $(tail -n 1 "$OUT/client_bomb.log")"
    [ "$rc_valid" = 0 ] || { echo "the valid example failed:"; cat "$OUT/client_valid.log"; return 1; }
    [ "$rc_bomb" != 0 ] && grep -q pose_3d "$OUT/client_bomb.log" || { echo "the bomb was not refused naming pose_3d"; return 1; }
    [ "$rss_bomb" -le $((rss_valid + 8192)) ] || { echo "the bomb took more memory than the valid file"; return 1; }
}
echo "case bomb: blapose-client on a 2 GiB zip-bomb replay file"
run_case bomb bomb_case
stop_server
kill "$REPLICA_PID" 2>/dev/null || true
wait "$REPLICA_PID" 2>/dev/null || true

if [ ${#failed[@]} -gt 0 ]; then
    echo "abuse: FAILED: ${failed[*]}" >&2
    exit 1
fi
echo "abuse: all cases hold"
