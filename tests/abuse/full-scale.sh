#!/usr/bin/env bash
# The abuse cases at the scale of the reports that motivated the limits,
# by hand (minutes; not in .ci/run, whose tests/abuse/run.sh runs them
# scaled down). Each server runs with the default limits (the memory
# budget: half the machine's or cgroup's memory, logged at start), each
# case beside the healthy client on 127.0.0.1:
#   pending   512 connections x 1,000 HEADERS-only streams from one address
#             (peak RSS growth at most 512 MB), then from 8 addresses (at
#             most 1 GB: 4,096 connections are accounted at 264 KB each,
#             1.06 GB); no address past --max-streams-per-peer (4,096)
#   churn     one client opening and closing 2,000,000 sessions with
#             --session-key (remembered ended sessions, bounded by
#             --max-ended-sessions): peak RSS growth at most 64 MB
#   dirbomb   8,000,000 directory entries more (a 416 MB file): both
#             readers refuse it under 64 MB
# The numbers are in tests/abuse/README.md. OUT needs about 1.5 GB: the
# churning server logs each session (about 1 GB for 2 M), the bomb 416 MB.
# Usage: tests/abuse/full-scale.sh [OUT_DIR]   (logs kept in OUT_DIR when given;
# $BLAPOSE_ABUSE_CASES picks some of "pending churn dirbomb", default all)
set -euo pipefail
cd "$(dirname "$0")/../.."
. tests/e2e-lib.sh
. tests/abuse/lib.sh

STARTED=$SECONDS
abuse_setup "${1:-}"

CASES=" ${BLAPOSE_ABUSE_CASES:-pending churn dirbomb} "
failed=()
if [[ $CASES == *" pending "* ]]; then
    for run in 1:512 8:1024; do
        addresses=${run%:*}
        start_server "$OUT/pending$addresses.log" --max-queue-delay 0
        grep -o 'memory budget.*' "$OUT/pending$addresses.log"
        "$ABUSE" pending --server "$URL" --server-pid "$SERVER_PID" --addresses "$addresses" \
            --connections 512 --streams 1000 --limit 4096 --max-growth-mb "${run#*:}" || failed+=("pending$addresses")
        stop_server
    done
fi

if [[ $CASES == *" churn "* ]]; then
    start_server "$OUT/churn.log" --max-queue-delay 0 --session-key "$KEY"
    "$ABUSE" churn --server "$URL" --server-pid "$SERVER_PID" --sessions 2000000 || failed+=(churn)
    stop_server
fi

if [[ $CASES == *" dirbomb "* ]]; then
    "$ABUSE" dirbomb --out "$OUT/dirbomb.npz" --entries 8000000
    URL=http://127.0.0.1:1  # no server: the readers refuse the file before they connect
    client_refuses "$OUT/dirbomb.npz" || failed+=(dirbomb-client)
    python_refuses "$OUT/dirbomb.npz" || failed+=(dirbomb-python)
    rm -f "$OUT/dirbomb.npz"
fi
echo "full scale: ${failed[*]:-all hold}${failed[*]:+ FAILED} ($((SECONDS - STARTED)) s)"
[ ${#failed[@]} -eq 0 ]
