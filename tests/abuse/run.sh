#!/usr/bin/env bash
# The server's limits under abuse, on loopback, bounded (under three minutes
# on the 2-core VM; the total time is printed): each case asserts its limit,
# the server's peak memory growth (at most 64 MB unless a case says
# otherwise) and a healthy client's latency (p99 within 2x of its baseline,
# measured in the same run, at least 5 ms; a new connection and session
# from 127.0.0.1, so a new client must be served), with the driver
# bench/src/bin/abuse/. Attackers come from 127.0.0.2 and up.
#   streams   many streams on one HTTP/2 connection (--max-concurrent-streams)
#   pending   4 addresses x 4 connections x 500 HEADERS-only streams
#             (--max-streams-per-peer 1000, --memory-budget 256M): no
#             address holds more than its limit
#   sessions  one client opening sessions as fast as it can while another
#             streams (--max-sessions-per-client, clients told apart by
#             --client-header from a trusted proxy)
#   shares2, shares8  2 (8) addresses each holding as many of 256 sessions
#             as they can, then sending frames they never read the answers
#             of: each is refused at some point, together they leave room,
#             and a new client opens a session and is served in turn. Its
#             p99 bound is 10 ms, not 5: the readers' frames keep the one
#             batcher busy, and a new client's frame waits for the 16-frame
#             step in progress (--max-mixed-batch) and runs in the next
#             (measured p50 1.6-1.7 ms, p99 2.5-7.4 ms on the 2-core VM, the
#             abusers on the same cores; tests/abuse/README.md)
#   churn     one client opening and closing 20,000 sessions, two at a time
#             (--session-key, --max-ended-sessions 5000): memory bounded
#   proxy6    --addr [::]:0 (IPv4 peers arrive as ::ffff:a.b.c.d) with
#             --trusted-proxies 127.0.0.1: the balancer's --client-header
#             names each client, 127.0.0.2's is ignored
#   token     one session token resumed on two replicas sharing a key: one
#             live copy per replica, refused after close, and after the
#             first token's TTL neither it nor a token the other replica's
#             copy issued restores the closed session on either replica
#   bomb      blapose-client on a replay file whose pose_3d is 2 GiB of
#             zeros deflated to 2 MB: refused, naming pose_3d, with the
#             client's peak RSS no more than on the valid example
#   dirbomb   a valid replay file with 200,000 central-directory entries
#             more (10 MB): blapose-client replay and Python's load_replay
#             both refuse it naming the entries, each under 64 MB peak RSS
#             (Python: $BLAPOSE_PYTHON, default target/pyvenv-ci/bin/python
#             as .ci/run makes it; skipped with a message when blapose does
#             not import there, except under CI=true)
#   idle      400 connections from 8 addresses that send the preface and
#             only answer PINGs: GOAWAY within --max-connection-idle + 10 s
#   flood     one connection flooding WINDOW_UPDATE frames: GOAWAY within
#             a second (--max-control-frames-per-second)
# A limit the server does not enforce fails its case with "not enforced".
# The servers run with --max-queue-delay 0: a lone stream (the baseline)
# never waits for a batch, while any concurrent stream makes it wait up to
# the batching delay (1 ms by default) by design; without the wait the
# latency check sees what the abuse costs, not the batching policy.
# The full-scale runs (by hand, not here) are in tests/abuse/README.md.
# Usage: tests/abuse/run.sh [OUT_DIR]   (logs kept in OUT_DIR when given)
set -euo pipefail
cd "$(dirname "$0")/../.."
. tests/e2e-lib.sh
. tests/abuse/lib.sh

STARTED=$SECONDS
abuse_setup "${1:-}"
STREAM_LIMIT=64
SESSION_LIMIT=8
failed=()

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

start_server "$OUT/pending.log" --max-queue-delay 0 --max-streams-per-peer 1000 --memory-budget 256M
run_case pending "$ABUSE" pending --server "$URL" --server-pid "$SERVER_PID" \
    --addresses 4 --connections 4 --streams 500 --limit 1000
stop_server

start_server "$OUT/sessions.log" --max-queue-delay 0 --client-header x-blapose-client --trusted-proxies 127.0.0.1 \
    --max-sessions-per-client "$SESSION_LIMIT"
run_case sessions "$ABUSE" sessions --server "$URL" --server-pid "$SERVER_PID" \
    --header x-blapose-client --attempts 200 --limit "$SESSION_LIMIT"
stop_server

# A server each: the sessions an earlier case dropped stay detached (and
# counted) for --session-ttl.
for k in 2 8; do
    start_server "$OUT/shares$k.log" --max-queue-delay 0 --max-sessions 256
    run_case "shares$k" "$ABUSE" shares --server "$URL" --server-pid "$SERVER_PID" --addresses "$k" --max-sessions 256 \
        --p99-floor-ms 10
    stop_server
done

start_server "$OUT/churn.log" --max-queue-delay 0 --session-key "$KEY" --max-ended-sessions 5000
run_case churn "$ABUSE" churn --server "$URL" --server-pid "$SERVER_PID" --sessions 20000
stop_server

SERVER_ADDR='[::]:0' start_server "$OUT/proxy6.log" --max-queue-delay 0 --client-header x-blapose-client \
    --trusted-proxies 127.0.0.1 --max-sessions-per-client "$SESSION_LIMIT"
run_case proxy6 "$ABUSE" proxy6 --server "$URL" --server-pid "$SERVER_PID" \
    --header x-blapose-client --limit "$SESSION_LIMIT"
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

dirbomb_case() {
    local ok=0
    "$ABUSE" dirbomb --out "$OUT/dirbomb.npz" --entries 200000
    client_refuses "$OUT/dirbomb.npz" || ok=1
    if "$PY" -c 'import blapose' 2>/dev/null; then
        python_refuses "$OUT/dirbomb.npz" || ok=1
    elif [ "${CI:-}" = true ]; then
        echo "  $PY cannot import blapose (CI=true: the Python half must run; .ci/run makes target/pyvenv-ci)"
        ok=1
    else
        echo "  SKIP the Python half: $PY cannot import blapose (set BLAPOSE_PYTHON, or run .ci/run once)"
    fi
    return $ok
}
echo "case dirbomb: a replay file with 200,000 zip directory entries more"
run_case dirbomb dirbomb_case
stop_server
kill "$REPLICA_PID" 2>/dev/null || true
wait "$REPLICA_PID" 2>/dev/null || true

if [ ${#failed[@]} -gt 0 ]; then
    echo "abuse: FAILED: ${failed[*]} ($((SECONDS - STARTED)) s)" >&2
    exit 1
fi
echo "abuse: all cases hold ($((SECONDS - STARTED)) s, the build included)"
