# Helpers of tests/abuse/run.sh and tests/abuse/full-scale.sh (sourced
# after tests/e2e-lib.sh, from the repository root; they use OUT, URL,
# CLIENT and PY).

# abuse_setup [OUT_DIR]: builds the server, the client and the driver,
# makes OUT (kept when OUT_DIR is given) and sets ABUSE, CLIENT, PY (the
# Python with the blapose package: $BLAPOSE_PYTHON, else the venv .ci/run
# makes) and KEY (a session key the replicas share).
abuse_setup() {
    # Two builds: --bin selects targets in every package named with it,
    # so one command would build the driver alone.
    build_release -p blapose-server -p blapose-client
    build_release -p blapose-bench --bin abuse
    use_out_dir "${1:-}"
    ABUSE=target/release/abuse
    CLIENT=target/release/blapose-client
    PY=${BLAPOSE_PYTHON:-target/pyvenv-ci/bin/python}
    KEY=hex:00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff
}

stop_server() {
    kill "$SERVER_PID" 2>/dev/null || true
    wait "$SERVER_PID" 2>/dev/null || true
    SERVER_PID=
}

# peak_rss_kb LOG CMD...: runs CMD (its output in LOG), prints its exit
# status and its peak RSS in kB.
peak_rss_kb() {
    local log=$1
    shift
    python3 - "$log" "$@" <<'PY'
import resource, subprocess, sys
with open(sys.argv[1], "w") as log:
    rc = subprocess.run(sys.argv[2:], stdout=log, stderr=subprocess.STDOUT).returncode
print(rc, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
PY
}

# refused_under LOG WHAT NEEDLE CMD...: CMD must fail naming NEEDLE, its
# peak RSS under DIRBOMB_RSS_MB.
DIRBOMB_RSS_MB=64
refused_under() {
    local log=$1 what=$2 needle=$3 rc rss
    shift 3
    read -r rc rss < <(peak_rss_kb "$log" "$@")
    echo "  $what: exit $rc, peak RSS $((rss / 1024)) MB: $(tail -n 1 "$log")"
    [ "$rc" != 0 ] && grep -q "$needle" "$log" || { echo "  $what did not refuse it naming $needle"; return 1; }
    [ "$rss" -lt $((DIRBOMB_RSS_MB * 1024)) ] || { echo "  $what peaked at $((rss / 1024)) MB, over $DIRBOMB_RSS_MB MB"; return 1; }
}

# client_refuses FILE, python_refuses FILE: blapose-client replay and
# Python's load_replay refuse the directory bomb FILE, naming its entries,
# under DIRBOMB_RSS_MB.
client_refuses() {
    refused_under "$OUT/client_dirbomb.log" "blapose-client replay" entries \
        "$CLIENT" --server "$URL" replay "$1"
}
python_refuses() {
    refused_under "$OUT/python_dirbomb.log" "Python load_replay" entries \
        "$PY" -c 'import sys, blapose; blapose.load_replay(sys.argv[1])' "$1"
}
