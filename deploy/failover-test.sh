#!/usr/bin/env bash
# Failover, tested for real: three blapose replicas sharing a session key,
# HAProxy in front of them (deploy/haproxy.cfg), all on loopback, and
# 32 sessions streaming the example sequences through the balancer.
#
#   1. frames/s of one replica alone, then of three behind the balancer
#      (unpaced; on one machine the replicas share its cores);
#   2. SIGKILL: one replica is killed mid-stream; every session on it
#      resumes on another replica from its latest session token;
#   3. SIGTERM: the killed replica is restarted, then another one is
#      drained; its sessions get a final token and resume elsewhere;
#   4. the session-token rules and per-client limits through HAProxy
#      (server/tests/integration/haproxy.rs: two in-process replicas behind it).
#
# Each case passes only if no frame is lost or answered twice and every
# bone length equals the undisturbed run's within 1e-6 m (the `failover`
# binary in bench/ checks it).
#
#   deploy/failover-test.sh [--json PATH] [--sessions N] [--fps F]
#                           [--image TAG [--engine podman|docker]]
#
# With --image the replicas are containers of that image (host network,
# e.g. one built by docker/build-local.sh), signalled through their init
# process; otherwise they are this checkout's release binary.
#
# Needs haproxy (installed with apt-get when missing and run as root) and
# builds blapose-server and the failover binary in release mode.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=../tests/e2e-lib.sh
. tests/e2e-lib.sh  # build_release

json=""
sessions=32
fps=40
image=""
engine=podman
while [[ $# -gt 0 ]]; do
    case "$1" in
        --json) json="$2"; shift 2 ;;
        --sessions) sessions="$2"; shift 2 ;;
        --fps) fps="$2"; shift 2 ;;
        --image) image="$2"; shift 2 ;;
        --engine) engine="$2"; shift 2 ;;
        -h|--help) sed -n '2,29p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "unknown argument: $1 (see --help)" >&2; exit 2 ;;
    esac
done

if ! command -v haproxy >/dev/null; then
    if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null; then
        echo "== installing haproxy (apt-get)"
        apt-get update -qq >/dev/null
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq haproxy >/dev/null
    else
        echo "haproxy is not installed (Debian: apt-get install haproxy)" >&2
        exit 1
    fi
fi

echo "== building blapose-server and the failover check"
build_release -p blapose-server -p blapose-bench --bin blapose-server --bin failover
server=target/release/blapose-server
failover=target/release/failover

if [[ -n "$image" ]] && ! "$engine" image exists "$image" 2>/dev/null &&
    ! "$engine" image inspect "$image" >/dev/null 2>&1; then
    echo "no image $image in $engine (build one with docker/build-local.sh)" >&2
    exit 1
fi

work=$(mktemp -d -t blapose-failover.XXXXXX)
pids=()
containers=()
haproxy_pid=""
cleanup() {
    for pid in "${pids[@]}" $haproxy_pid; do
        kill "$pid" 2>/dev/null || true
    done
    for c in "${containers[@]}"; do
        "$engine" rm -f "$c" >/dev/null 2>&1 || true
    done
    wait 2>/dev/null || true
    rm -rf "$work"
}
trap cleanup EXIT

free_port() {
    python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'
}

key="hex:$(python3 -c 'import secrets; print(secrets.token_hex(32))')"
ports=("$(free_port)" "$(free_port)" "$(free_port)")
lb_port=$(free_port)
stats_port=$(free_port)

start_replica() { # index
    local i=$1
    if [[ -n "$image" ]]; then
        local name="blapose-failover-$$-$((i + 1))-$RANDOM"
        if [[ -n "${containers[$i]:-}" ]]; then
            "$engine" rm -f "${containers[$i]}" >/dev/null 2>&1 || true
        fi
        # --no-healthcheck: HAProxy checks the replicas itself (and podman
        # without systemd cannot schedule the image's HEALTHCHECK).
        "$engine" run -d --no-healthcheck --name "$name" --network host \
            -e BLAPOSE_SESSION_KEY="$key" -e BLAPOSE_ADDR="127.0.0.1:${ports[$i]}" \
            -e BLAPOSE_CLIENT_HEADER=x-blapose-client -e BLAPOSE_TRUSTED_PROXIES=127.0.0.1 \
            "$image" --no-metrics --token-every 25 --shutdown-grace 10s >/dev/null
        containers[$i]=$name
        # The container's init (tini), which forwards SIGTERM to the server;
        # SIGKILL to it ends the container at once.
        pids[$i]=$("$engine" inspect -f '{{.State.Pid}}' "$name")
    else
        BLAPOSE_SESSION_KEY="$key" BLAPOSE_CLIENT_HEADER=x-blapose-client \
            BLAPOSE_TRUSTED_PROXIES=127.0.0.1 "$server" --addr "127.0.0.1:${ports[$i]}" --no-metrics \
            --token-every 25 --shutdown-grace 10s >>"$work/replica$((i + 1)).log" 2>&1 &
        pids[$i]=$!
    fi
    for _ in $(seq 1 100); do
        if "$server" --health-check --addr "127.0.0.1:${ports[$i]}" >/dev/null 2>&1; then
            return 0
        fi
        sleep 0.1
    done
    echo "replica $((i + 1)) did not become healthy; its log:" >&2
    replica_log "$i" >&2
    exit 1
}

replica_log() { # index
    if [[ -n "$image" ]]; then
        "$engine" logs "${containers[$1]}" 2>&1 || true
    else
        cat "$work/replica$(($1 + 1)).log"
    fi
}

# Wait for replica `index` to exit; its exit status.
replica_exit() { # index
    if [[ -n "$image" ]]; then
        "$engine" wait "${containers[$1]}" 2>/dev/null | tail -n 1
    else
        local status=0
        wait "${pids[$1]}" 2>/dev/null || status=$?
        echo "$status"
    fi
}

# The balancer's view: how many replicas it has UP.
replicas_up() {
    curl -fsS "http://127.0.0.1:$stats_port/;csv" 2>/dev/null |
        awk -F, '$1 == "blapose" && $2 ~ /^replica/ && $18 == "UP"' | wc -l
}

wait_up() { # count
    for _ in $(seq 1 100); do
        if [[ $(replicas_up) -eq $1 ]]; then
            return 0
        fi
        sleep 0.1
    done
    echo "HAProxy does not see $1 replicas up; its log:" >&2
    cat "$work/haproxy.log" >&2
    exit 1
}

echo "== three replicas${image:+ (containers of $image)} and HAProxy on loopback (balancer :$lb_port)"
for i in 0 1 2; do
    start_replica "$i"
done
BLAPOSE_LB_ADDR="127.0.0.1:$lb_port" BLAPOSE_LB_STATS="127.0.0.1:$stats_port" \
    BLAPOSE_REPLICA_1="127.0.0.1:${ports[0]}" BLAPOSE_REPLICA_2="127.0.0.1:${ports[1]}" \
    BLAPOSE_REPLICA_3="127.0.0.1:${ports[2]}" \
    haproxy -db -f deploy/haproxy.cfg >"$work/haproxy.log" 2>&1 &
haproxy_pid=$!
wait_up 3
lb="http://127.0.0.1:$lb_port"

echo "== throughput: $sessions sessions, one replica alone"
"$failover" --server "http://127.0.0.1:${ports[0]}" --sessions "$sessions" --throughput \
    --json "$work/one.json"
echo "== throughput: $sessions sessions, three replicas behind HAProxy"
"$failover" --server "$lb" --sessions "$sessions" --throughput --json "$work/three.json"

echo "== SIGKILL replica 1 mid-stream"
"$failover" --server "$lb" --sessions "$sessions" --fps "$fps" \
    --victim-pid "${pids[0]}" --signal kill --json "$work/kill.json"
replica_exit 0 >/dev/null

echo "== restart replica 1, then SIGTERM (drain) replica 2 mid-stream"
start_replica 0
wait_up 3
"$failover" --server "$lb" --sessions "$sessions" --fps "$fps" \
    --victim-pid "${pids[1]}" --signal term --json "$work/drain.json"
drain_status=$(replica_exit 1)
if [[ "$drain_status" != 0 ]]; then
    echo "the drained replica exited with status $drain_status, not 0; its log:" >&2
    replica_log 1 >&2
    exit 1
fi

report=$(python3 - "$work" <<'EOF'
import json, sys
d = sys.argv[1]
load = lambda name: json.load(open(f"{d}/{name}.json"))
report = load("kill")
report["drain"] = load("drain")
one, three = load("one"), load("three")
report["throughput"] = {
    "sessions": one["sessions"],
    "one_replica_fps": round(one["frames_per_second"], 1),
    "three_replicas_fps": round(three["frames_per_second"], 1),
}
print(json.dumps(report, indent=2))
EOF
)
echo "$report"

echo "== token rules and per-client limits behind HAProxy (server/tests/integration/haproxy.rs)"
# --workspace, not -p blapose-server: the same package selection as
# `cargo test --workspace --release`, so the test binary that built is run
# as it is instead of the server being compiled again for a smaller
# selection's features (only the server's integration tests match).
BLAPOSE_REQUIRE_HAPROXY=1 cargo test --release --quiet --workspace --test integration haproxy::

if [[ -n "$json" ]]; then
    echo "$report" >"$json"
    echo "wrote $json"
fi
echo "failover test passed"
