#!/usr/bin/env bash
# Smoke test of a built blapose-server image, run from the host:
#
#   1. plaintext: run with the gRPC and metrics ports published on random
#      free 127.0.0.1 ports; wait for `blapose-server --health-check` inside
#      the container (and the image's own HEALTHCHECK); check the server runs
#      as uid 10001; replay examples/cmu_02_02_walk.npz through the published
#      port with the host's blapose-client (bone error must drop); scrape
#      /metrics; stop it (SIGTERM, timed) and check exit code 0 and the
#      graceful-shutdown log line.
#   2. TLS: a self-signed certificate for localhost (openssl, temp dir)
#      mounted read-only, BLAPOSE_TLS_CERT/BLAPOSE_TLS_KEY set; the in-image
#      health check over TLS, a replay over https://localhost:PORT with
#      --tls-ca, then the same graceful stop.
#
# Skips (exit 0, "SKIP: ...") with no container engine, and under CI=true
# (CI runners have none) unless --force. Exit 1 when a check fails.
#
#   docker/smoke-test.sh                       # blapose-server:latest
#   docker/smoke-test.sh --json /tmp/smoke.json blapose-server:dev
set -euo pipefail

usage() {
    cat <<'EOF'
Usage: docker/smoke-test.sh [OPTIONS] [IMAGE]

Run the blapose-server IMAGE (default: blapose-server:latest) and check
health, replay through the published port, uid, TLS and graceful stop.

Options:
  --engine NAME   podman or docker (default: podman if installed, else docker
                  if its daemon answers; neither: SKIP)
  --json PATH     write {image_size_mb, health_s, replay_ok, uid_ok,
                  metrics_ok, tls_ok, stop_s, tls_stop_s, ...}
  --client PATH   the host's blapose-client (default:
                  target/release/blapose-client, built if missing)
  --force         run even when CI=true
  --keep          leave the containers and the TLS temp dir for inspection
  -h, --help      show this help
EOF
}

engine=""
client=""
image=""
json_out=""
force=0
keep=0
while [[ $# -gt 0 ]]; do
    case "$1" in
        --engine) engine=${2:?--engine needs a value}; shift 2 ;;
        --json) json_out=${2:?--json needs a path}; shift 2 ;;
        --client) client=${2:?--client needs a path}; shift 2 ;;
        --force) force=1; shift ;;
        --keep) keep=1; shift ;;
        -h|--help) usage; exit 0 ;;
        -*) usage >&2; echo "smoke-test.sh: unknown option: $1" >&2; exit 2 ;;
        *) image=$1; shift ;;
    esac
done
image=${image:-blapose-server:latest}

repo_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
replay_file="$repo_root/examples/cmu_02_02_walk.npz"
client=${client:-$repo_root/target/release/blapose-client}

have() { command -v "$1" >/dev/null 2>&1; }
log() { printf '==> %s\n' "$*"; }
skip() { echo "SKIP: $*"; exit 0; }
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.2f", b - a }'; }

if [[ ${CI:-} == true && $force -eq 0 ]]; then
    skip "CI=true: CI runners have no container engine (docker/smoke-test.sh --force runs it anyway)"
fi

if [[ -z $engine ]]; then
    if have podman; then engine=podman
    elif have docker && docker info >/dev/null 2>&1; then engine=docker
    else skip "no container engine (podman, or docker with a daemon)"; fi
fi
have "$engine" || skip "no container engine: $engine not installed"
if [[ $engine == docker ]] && ! docker info >/dev/null 2>&1; then
    skip "no container engine: docker has no daemon"
fi

if ! "$engine" image inspect "$image" >/dev/null 2>&1; then
    echo "smoke-test.sh: image $image not found in $engine; build it with docker/build-local.sh" >&2
    exit 1
fi
have openssl || { echo "smoke-test.sh: openssl needed for the TLS check" >&2; exit 1; }
if [[ ! -x $client && $client == "$repo_root/target/release/blapose-client" ]]; then
    log "building blapose-client (host)"
    (cd "$repo_root" && nice -n 19 cargo build --release -p blapose-client)
fi
[[ -x $client ]] || { echo "smoke-test.sh: no blapose-client at $client" >&2; exit 1; }

# --- state and cleanup -------------------------------------------------------

run_id="blapose-smoke-$$"
containers=()
tls_dir=""
err_file=$(mktemp /tmp/blapose-smoke-err.XXXXXX)
failures=()
cleanup() {
    if [[ $keep -eq 1 ]]; then
        [[ ${#containers[@]} -gt 0 ]] && echo "kept containers: ${containers[*]}"
        [[ -n $tls_dir ]] && echo "kept TLS dir: $tls_dir"
        return
    fi
    local c
    rm -f "$err_file"
    for c in "${containers[@]}"; do "$engine" rm -f "$c" >/dev/null 2>&1 || true; done
    [[ -n $tls_dir ]] && rm -rf "$tls_dir"
}
trap cleanup EXIT

check() { # check NAME CONDITION-RESULT(0/1) DETAIL
    if [[ $2 -eq 0 ]]; then echo "  ok    $1${3:+: $3}"
    else echo "  FAIL  $1${3:+: $3}"; failures+=("$1"); fi
}

# --- steps -------------------------------------------------------------------

start() { # start NAME [engine run args...]; prints nothing, sets $cid
    local name=$1; shift
    cid=$("$engine" run -d --name "$name" \
        -p 127.0.0.1::50051 -p 127.0.0.1::9090 "$@" "$image" 2>"$err_file") \
        || { cat "$err_file" >&2; return 1; }
    quiet "$err_file"
    containers+=("$name")
}

# podman without systemd (containers, CI) cannot schedule the HEALTHCHECK
# timer and says so on every run and stop; the check itself is run by hand
# here. (A file, not a pipe: podman's conmon keeps the stderr it was given.)
quiet() { grep -v 'systemd connection' "$1" >&2 || true; }

host_port() { # host_port CONTAINER CONTAINER_PORT -> the published 127.0.0.1 port
    "$engine" port "$1" "$2/tcp" | grep -m1 '127.0.0.1' | sed 's/.*://'
}

wait_healthy() { # wait_healthy CONTAINER STARTED_AT -> sets health_took (s) or fails
    local c=$1 t0=$2 deadline=$((SECONDS + 60))
    health_took=""
    while [[ $SECONDS -lt $deadline ]]; do
        if "$engine" exec "$c" blapose-server --health-check >/dev/null 2>&1; then
            health_took=$(since "$t0")
            return 0
        fi
        if [[ $("$engine" inspect --format '{{.State.Running}}' "$c") != true ]]; then
            echo "  container $c exited:"; "$engine" logs "$c" 2>&1 | tail -20 | sed 's/^/    /'
            return 1
        fi
        sleep 0.25
    done
    return 1
}

image_healthcheck() { # the image's own HEALTHCHECK (needs the docker image format under podman)
    local c=$1
    if [[ $engine == podman ]]; then
        podman healthcheck run "$c" >/dev/null 2>&1
    else
        local deadline=$((SECONDS + 40)) status
        while [[ $SECONDS -lt $deadline ]]; do
            status=$(docker inspect --format '{{if .State.Health}}{{.State.Health.Status}}{{end}}' "$c")
            [[ $status == healthy ]] && return 0
            [[ -z $status ]] && return 1
            sleep 1
        done
        return 1
    fi
}

server_uid() { # the uid of the server process (PID 1 is tini; the server is its child)
    local c=$1 pid child
    pid=$("$engine" inspect --format '{{.State.Pid}}' "$c")
    if [[ -r /proc/$pid/task/$pid/children ]]; then
        child=$(awk '{print $1}' "/proc/$pid/task/$pid/children")
        awk '/^Uid:/ {print $2}' "/proc/${child:-$pid}/status"
    else # the engine runs in a VM: ask it
        "$engine" top "$c" -eo uid,args 2>/dev/null | awk '/blapose-server/ && !/tini/ {print $1; exit}'
    fi
}

replay() { # replay URL [client args...] -> sets replay_out; 0 when bone error dropped
    local url=$1; shift
    replay_out=$("$client" --server "$url" "$@" replay "$replay_file" 2>&1) || return 1
    awk '/^bone error/ { exit !($5 < $4) } END { if (NR == 0) exit 1 }' <<<"$replay_out" \
        && grep -q '^bone error' <<<"$replay_out"
}

stop_gracefully() { # stop_gracefully CONTAINER -> sets stop_took; 0 when exit 0 + shutdown log
    local c=$1 t0 code
    t0=$(now)
    "$engine" stop -t 20 "$c" >/dev/null 2>"$err_file" || { cat "$err_file" >&2; return 1; }
    quiet "$err_file"
    stop_took=$(since "$t0")
    code=$("$engine" inspect --format '{{.State.ExitCode}}' "$c")
    stop_code=$code
    [[ $code == 0 ]] && "$engine" logs "$c" 2>&1 | grep -q 'server stopped'
}

size_bytes=$("$engine" image inspect --format '{{.Size}}' "$image")
image_size_mb=$(awk -v b="$size_bytes" 'BEGIN { printf "%.1f", b / 1e6 }')
echo "image $image ($image_size_mb MB), engine: $("$engine" --version)"

# 1. plaintext
log "plaintext run"
t0=$(now)
start "$run_id-plain" -p 127.0.0.1::8080 -e BLAPOSE_WEB_ADDR=0.0.0.0:8080
c="$run_id-plain"
grpc_port=$(host_port "$c" 50051)
web_port=$(host_port "$c" 8080)
metrics_port=$(host_port "$c" 9090)
echo "  ports: gRPC 127.0.0.1:$grpc_port, metrics 127.0.0.1:$metrics_port"

health_ok=false; health_s=null
if wait_healthy "$c" "$t0"; then health_ok=true; health_s=$health_took; fi
check "health (blapose-server --health-check in the container)" $([[ $health_ok == true ]]; echo $?) "${health_s}s after start"

image_hc_ok=false
image_healthcheck "$c" && image_hc_ok=true
check "image HEALTHCHECK" $([[ $image_hc_ok == true ]]; echo $?)

uid=$(server_uid "$c" || true)
uid_ok=false; [[ $uid == 10001 ]] && uid_ok=true
check "server runs as uid 10001" $([[ $uid_ok == true ]]; echo $?) "uid ${uid:-unknown}"

replay_ok=false
replay "http://127.0.0.1:$grpc_port" && replay_ok=true
check "replay through the published port" $([[ $replay_ok == true ]]; echo $?) \
    "$(grep -m1 '^bone error' <<<"$replay_out" || tail -3 <<<"$replay_out")"

metrics_ok=false
if have curl; then
    curl -fsS "http://127.0.0.1:$metrics_port/metrics" 2>/dev/null | grep -q '^blapose_' && metrics_ok=true
    check "metrics on the published port" $([[ $metrics_ok == true ]]; echo $?)
fi

web_ok=false
if have curl; then
    curl -fsS "http://127.0.0.1:$web_port/" 2>/dev/null | grep -q '<title>blapose live' \
        && curl -fsS -o /dev/null "http://127.0.0.1:$web_port/vendor/mediapipe/pose_landmarker_lite.task" \
        && web_ok=true
    check "the live page on the published port (--web-addr, the image's web/dist)" $([[ $web_ok == true ]]; echo $?)
fi

# The page's download: a two-frame take posted to the export route comes back as BVH.
export_ok=false
if have curl && have python3; then
    take=$(python3 -c 'import json
pose = [v for j in range(17) for v in (0.05 * j, -0.1 * j, 3.0 + 0.02 * (j % 3))]
print(json.dumps({"fps": 30, "layout": "coco17", "image_size": [640, 480],
    "keypoints_2d": [200.0] * 68, "pose_3d": pose * 2, "adjusted": pose * 2,
    "bone_lengths": [0.1] * 16}))')
    curl -fsS -H 'content-type: application/json' --data "$take" \
        "http://127.0.0.1:$web_port/v1/export/bvh" 2>/dev/null | head -c 9 | grep -q HIERARCHY \
        && export_ok=true
    check "the take as BVH from the page's export route" $([[ $export_ok == true ]]; echo $?)
fi

stop_ok=false; stop_s=null
stop_gracefully "$c" && stop_ok=true
stop_s=$stop_took
check "graceful stop (SIGTERM)" $([[ $stop_ok == true ]]; echo $?) "${stop_s}s, exit code $stop_code"

# 2. TLS
log "TLS run"
tls_dir=$(mktemp -d /tmp/blapose-smoke-tls.XXXXXX)
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 2 \
    -subj /CN=localhost -addext 'subjectAltName=DNS:localhost,IP:127.0.0.1' \
    -addext 'basicConstraints=critical,CA:FALSE' \
    -keyout "$tls_dir/key.pem" -out "$tls_dir/cert.pem" 2>/dev/null
# The server runs as uid 10001; this throwaway key must be readable by it.
chmod 0755 "$tls_dir"; chmod 0644 "$tls_dir/key.pem" "$tls_dir/cert.pem"
t0=$(now)
start "$run_id-tls" -v "$tls_dir:/tls:ro" \
    -e BLAPOSE_TLS_CERT=/tls/cert.pem -e BLAPOSE_TLS_KEY=/tls/key.pem
c="$run_id-tls"
tls_port=$(host_port "$c" 50051)
echo "  port: gRPC (TLS) localhost:$tls_port"

tls_health_ok=false; tls_health_s=null
if wait_healthy "$c" "$t0"; then tls_health_ok=true; tls_health_s=$health_took; fi
check "health over TLS (in the container)" $([[ $tls_health_ok == true ]]; echo $?) "${tls_health_s}s after start"

tls_replay_ok=false
replay "https://localhost:$tls_port" --tls-ca "$tls_dir/cert.pem" && tls_replay_ok=true
check "replay over TLS (https://localhost, --tls-ca)" $([[ $tls_replay_ok == true ]]; echo $?) \
    "$(grep -m1 '^bone error' <<<"$replay_out" || tail -3 <<<"$replay_out")"

plain_refused=false
"$client" --server "http://127.0.0.1:$tls_port" --connect-timeout 2 info >/dev/null 2>&1 || plain_refused=true
check "plaintext refused on the TLS port" $([[ $plain_refused == true ]]; echo $?)

tls_ok=false
[[ $tls_health_ok == true && $tls_replay_ok == true && $plain_refused == true ]] && tls_ok=true

tls_stop_ok=false; tls_stop_s=null
stop_gracefully "$c" && tls_stop_ok=true
tls_stop_s=$stop_took
check "graceful stop, TLS (SIGTERM)" $([[ $tls_stop_ok == true ]]; echo $?) "${tls_stop_s}s, exit code $stop_code"

# --- summary -----------------------------------------------------------------

echo
echo "summary: image ${image_size_mb} MB, healthy after ${health_s}s, replay $replay_ok, uid $uid, TLS $tls_ok, stop ${stop_s}s / ${tls_stop_s}s (TLS)"
if [[ -n $json_out ]]; then
    cat >"$json_out" <<EOF
{"image":"$image","engine":"$engine","image_size_mb":$image_size_mb,"health_s":$health_s,"image_healthcheck_ok":$image_hc_ok,"uid_ok":$uid_ok,"replay_ok":$replay_ok,"metrics_ok":$metrics_ok,"web_ok":$web_ok,"export_ok":$export_ok,"stop_s":$stop_s,"stop_ok":$stop_ok,"tls_ok":$tls_ok,"tls_health_s":$tls_health_s,"tls_stop_s":$tls_stop_s,"tls_stop_ok":$tls_stop_ok,"failures":${#failures[@]}}
EOF
    echo "wrote $json_out"
fi
if [[ ${#failures[@]} -gt 0 ]]; then
    echo "FAILED: ${failures[*]}"
    exit 1
fi
echo "PASS"
