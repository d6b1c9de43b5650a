# Helpers sourced by the end-to-end scripts (tests/*/run.sh,
# deploy/failover-test.sh), run from the repository root.

# build_release ARGS...: `cargo build --release --quiet ARGS`, unless
# BLAPOSE_PREBUILT=1 says the binaries are built already. .ci/run sets it
# after its `cargo test --workspace --release`, which builds every binary
# these scripts run: a `cargo build -p ...` of a few packages resolves
# features for that selection alone and would compile the server and the
# client again (minutes on two cores).
build_release() {
    [ "${BLAPOSE_PREBUILT:-}" = 1 ] && return 0
    cargo build --release --quiet "$@"
}

# use_out_dir KEEP: OUT is KEEP (created, kept) when it is set, else a
# temporary directory; on exit the server (SERVER_PID) is stopped and a
# temporary OUT removed.
use_out_dir() {
    KEEP_OUT=$1
    if [ -n "$KEEP_OUT" ]; then
        OUT=$KEEP_OUT
        mkdir -p "$OUT"
    else
        OUT=$(mktemp -d)
    fi
    SERVER_PID=
    trap e2e_cleanup EXIT
}

e2e_cleanup() {
    if [ -n "$SERVER_PID" ]; then kill "$SERVER_PID" 2>/dev/null || true; wait "$SERVER_PID" 2>/dev/null || true; fi
    if [ -z "$KEEP_OUT" ]; then rm -rf "$OUT"; fi
}

# start_server LOG [ARGS...]: starts $BLAPOSE_SERVER_BIN (default
# target/release/blapose-server) on a free port (--addr $SERVER_ADDR,
# default 127.0.0.1:0; it logs the port it got) with ARGS, sets SERVER_PID
# and URL (always http://127.0.0.1:PORT: a [::] listener takes IPv4 too),
# and exits with the log when it does not come up.
start_server() {
    local log=$1 port
    shift
    # Emptied first: the server's own redirection may come after the first
    # look below, which would read an earlier run's port from a kept log.
    : >"$log"
    "${BLAPOSE_SERVER_BIN:-target/release/blapose-server}" --addr "${SERVER_ADDR:-127.0.0.1:0}" --no-metrics "$@" >"$log" 2>&1 &
    SERVER_PID=$!
    URL=
    for _ in $(seq 600); do
        port=$(sed -n 's/.*serving blapose\.v1 addr=[^ ]*:\([0-9]*\).*/\1/p' "$log" | head -n 1)
        if [ -n "$port" ]; then URL=http://127.0.0.1:$port; return 0; fi
        kill -0 "$SERVER_PID" 2>/dev/null || break
        sleep 0.1
    done
    echo "error: blapose-server did not start:" >&2
    cat "$log" >&2
    exit 1
}
