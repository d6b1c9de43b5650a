#!/usr/bin/env bash
# Offline checks of the deployment files; no cluster and no network needed
# except for PyPI on the first run (creating the venv).
#
#   deploy/validate.sh
#
# 1. Every YAML file under deploy/k8s (examples/ included) against the
#    Kubernetes OpenAPI schemas shipped in the `kubernetes-validate` PyPI
#    package, in strict mode (unknown fields fail), for the oldest and the
#    newest Kubernetes these manifests target. A document whose kind has no
#    schema (a typo in kind/apiVersion) fails too.
# 2. Consistency between the manifests (no namespaces; grace period covers
#    preStop + shutdown grace; gRPC probes on the gRPC port; Secret name/key
#    match; HAProxy resolves the headless Service; no real key committed).
# 3. The haproxy.cfg inside deploy/k8s/haproxy.yaml's ConfigMap: extracted
#    and checked with `haproxy -c`; its balance/hash/tcp-check/timeout lines
#    must be the same as deploy/haproxy.cfg's.
# 4. deploy/haproxy.cfg itself with `haproxy -c` (dummy addresses).
#
# The venv lives in target/k8s-validate-venv (created when missing).
# Environment: HAPROXY (default: haproxy on PATH, else /usr/sbin/haproxy),
# PYTHON (default python3), K8S_VERSIONS (default "1.30.0 1.37.0").
set -euo pipefail
cd "$(dirname "$0")/.."

KUBERNETES_VALIDATE_VERSION=1.37.0
# 1.30: first release with the preStop `sleep` action on by default (it is
# GA from 1.34); 1.37: the newest schema kubernetes-validate 1.37.0 ships.
K8S_VERSIONS=${K8S_VERSIONS:-"1.30.0 1.37.0"}
VENV=target/k8s-validate-venv
PYTHON=${PYTHON:-python3}
K8S_DIR=deploy/k8s

# --- haproxy present? (checked first: no point building a venv otherwise)
HAPROXY=${HAPROXY:-$(command -v haproxy || true)}
if [[ -z $HAPROXY && -x /usr/sbin/haproxy ]]; then HAPROXY=/usr/sbin/haproxy; fi
if [[ -z $HAPROXY || ! -x $HAPROXY ]]; then
    echo "deploy/validate.sh: haproxy not found${HAPROXY:+ at $HAPROXY} (needed for 'haproxy -c');" \
         "install it, e.g. 'apt-get install -y haproxy', or set HAPROXY=/path/to/haproxy" >&2
    exit 1
fi

# --- venv with kubernetes-validate
if [[ $("$VENV/bin/kubernetes-validate" --version 2>/dev/null || true) != "$KUBERNETES_VALIDATE_VERSION" ]]; then
    echo "== creating $VENV with kubernetes-validate==$KUBERNETES_VALIDATE_VERSION"
    rm -rf "$VENV"
    mkdir -p "$(dirname "$VENV")"
    "$PYTHON" -m venv "$VENV"
    "$VENV/bin/pip" install --quiet --disable-pip-version-check \
        "kubernetes-validate==$KUBERNETES_VALIDATE_VERSION"
fi
PY="$VENV/bin/python"   # has PyYAML (a kubernetes-validate dependency)

mapfile -t MANIFESTS < <(find "$K8S_DIR" -type f \( -name '*.yaml' -o -name '*.yml' \) | LC_ALL=C sort)
if (( ${#MANIFESTS[@]} == 0 )); then
    echo "deploy/validate.sh: no YAML files under $K8S_DIR" >&2
    exit 1
fi

TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT

# --- 1. schemas
for k in $K8S_VERSIONS; do
    echo "== kubernetes-validate $KUBERNETES_VALIDATE_VERSION --strict -k $k (${#MANIFESTS[@]} files)"
    # It exits non-zero on schema errors and unparsable YAML, but only warns
    # (exit 0) for a kind it has no schema for: treat that as a failure too.
    if ! "$VENV/bin/kubernetes-validate" --strict -k "$k" "${MANIFESTS[@]}" >"$TMP/kv.out" 2>&1; then
        cat "$TMP/kv.out" >&2
        echo "FAILED: manifests do not validate against Kubernetes $k" >&2
        exit 1
    fi
    if grep -qv '^INFO ' "$TMP/kv.out"; then
        cat "$TMP/kv.out" >&2
        echo "FAILED: kubernetes-validate warned (unknown kind/apiVersion?) for Kubernetes $k" >&2
        exit 1
    fi
    sed 's/^/  /' "$TMP/kv.out"
done

# --- 2. consistency, and extract the ConfigMap's haproxy.cfg
echo "== manifest consistency checks"
"$PY" - "$TMP/k8s-haproxy.cfg" "${MANIFESTS[@]}" <<'PYEOF'
import re, sys, yaml

out_cfg, files = sys.argv[1], sys.argv[2:]
docs = {}
errors = []
for f in files:
    with open(f) as fh:
        for d in yaml.safe_load_all(fh):
            if d is None:
                continue
            meta = d.get("metadata", {})
            if "namespace" in meta:
                errors.append(f"{f}: {d['kind']}/{meta.get('name')} sets a namespace")
            docs[(d["kind"], meta["name"])] = d

def need(key):
    if key not in docs:
        sys.exit(f"FAILED: missing {key[0]}/{key[1]}")
    return docs[key]

def seconds(s):
    m = re.fullmatch(r"(\d+)(ms|s|m)?", s)
    if not m:
        sys.exit(f"FAILED: cannot parse duration {s!r}")
    n, unit = int(m.group(1)), m.group(2) or "s"
    return n / 1000 if unit == "ms" else n * (60 if unit == "m" else 1)

server = need(("Deployment", "blapose-server"))
pod = server["spec"]["template"]["spec"]
c = pod["containers"][0]
env = {e["name"]: e for e in c.get("env", [])}
grace = seconds(env.get("BLAPOSE_SHUTDOWN_GRACE", {}).get("value", "10s"))
sleep = c["lifecycle"]["preStop"]["sleep"]["seconds"]
tgps = pod["terminationGracePeriodSeconds"]
if not tgps > sleep + grace:
    errors.append(f"terminationGracePeriodSeconds {tgps} <= preStop sleep {sleep}s + shutdown grace {grace}s")
for probe in ("readinessProbe", "livenessProbe"):
    g = c.get(probe, {}).get("grpc")
    if not g or g.get("port") != 50051:
        errors.append(f"blapose-server {probe} is not a gRPC probe on 50051")
ref = env.get("BLAPOSE_SESSION_KEY", {}).get("valueFrom", {}).get("secretKeyRef")
if not ref:
    errors.append("BLAPOSE_SESSION_KEY does not come from a Secret (secretKeyRef)")
else:
    secret = need(("Secret", ref["name"]))
    data = {**secret.get("stringData", {}), **secret.get("data", {})}
    if ref["key"] not in data:
        errors.append(f"Secret {ref['name']} example has no key {ref['key']!r}")
    elif re.fullmatch(r"hex:[0-9a-fA-F]{32,}|base64:.{22,}", str(data[ref["key"]])):
        errors.append(f"Secret {ref['name']} holds what looks like a real key: commit a placeholder only")
if ("PodDisruptionBudget", "blapose-server") not in docs:
    errors.append("no PodDisruptionBudget for blapose-server")

headless = need(("Service", "blapose-replicas"))
if headless["spec"].get("clusterIP") != "None":
    errors.append("Service blapose-replicas is not headless (clusterIP: None)")
if headless["spec"]["selector"] != server["spec"]["selector"]["matchLabels"]:
    errors.append("Service blapose-replicas does not select the blapose-server pods")
lb = need(("Deployment", "blapose-haproxy"))
lbenv = {e["name"]: e for e in lb["spec"]["template"]["spec"]["containers"][0].get("env", [])}
dns = lbenv.get("BLAPOSE_REPLICAS_DNS", {}).get("value", "")
if not dns.startswith("blapose-replicas.$(POD_NAMESPACE).svc."):
    errors.append(f"BLAPOSE_REPLICAS_DNS {dns!r} is not the headless Service's name")

cfg = need(("ConfigMap", "blapose-haproxy"))["data"]["haproxy.cfg"]
with open(out_cfg, "w") as fh:
    fh.write(cfg)
if errors:
    for e in errors:
        print("FAILED:", e, file=sys.stderr)
    sys.exit(1)
print(f"  {len(docs)} resources: no namespaces; grace {tgps}s > preStop {sleep}s + shutdown {grace:g}s;"
      " gRPC readiness/liveness on 50051; session key from Secret"
      f" {ref['name']}/{ref['key']} (placeholder only); HAProxy resolves {dns}")
PYEOF

# --- 3. the ConfigMap's haproxy.cfg
echo "== $HAPROXY -c: haproxy.cfg from the ConfigMap in $K8S_DIR/haproxy.yaml"
"$HAPROXY" -v 2>&1 | sed -n '1s/^/  /p'
# The name needs not resolve here: the slots start empty (init-addr none).
if ! BLAPOSE_REPLICAS_DNS=blapose-replicas.default.svc.cluster.local \
    "$HAPROXY" -c -f "$TMP/k8s-haproxy.cfg" >"$TMP/haproxy.out" 2>&1; then
    cat "$TMP/haproxy.out" >&2
    echo "FAILED: haproxy -c rejected the ConfigMap's haproxy.cfg" >&2
    exit 1
fi
sed 's/^/  /' "$TMP/haproxy.out"

# Lines that must not drift between the two configurations.
shared='^[[:space:]]*(balance|hash-type|option tcp-check|tcp-check|default-server|retries|option redispatch|timeout (connect|client|server|check))([[:space:]]|$)'
grep -E "$shared" deploy/haproxy.cfg | sed 's/^[[:space:]]*//' >"$TMP/shared.vm"
grep -E "$shared" "$TMP/k8s-haproxy.cfg" | sed 's/^[[:space:]]*//' >"$TMP/shared.k8s"
if ! diff -u "$TMP/shared.vm" "$TMP/shared.k8s" >"$TMP/shared.diff"; then
    cat "$TMP/shared.diff" >&2
    echo "FAILED: balance/hash/health-check/timeout lines differ between deploy/haproxy.cfg and the ConfigMap" >&2
    exit 1
fi
echo "  $(wc -l <"$TMP/shared.vm") balance/hash-type/tcp-check/default-server/timeout lines identical to deploy/haproxy.cfg"

# --- 4. deploy/haproxy.cfg
echo "== $HAPROXY -c: deploy/haproxy.cfg (dummy addresses)"
if ! BLAPOSE_LB_ADDR=127.0.0.1:50051 BLAPOSE_LB_STATS=127.0.0.1:8404 \
    BLAPOSE_REPLICA_1=127.0.0.1:50061 BLAPOSE_REPLICA_2=127.0.0.1:50062 \
    BLAPOSE_REPLICA_3=127.0.0.1:50063 \
    "$HAPROXY" -c -f deploy/haproxy.cfg >"$TMP/haproxy.out" 2>&1; then
    cat "$TMP/haproxy.out" >&2
    echo "FAILED: haproxy -c rejected deploy/haproxy.cfg" >&2
    exit 1
fi
sed 's/^/  /' "$TMP/haproxy.out"

echo "deploy/validate.sh: all passed (${#MANIFESTS[@]} manifest files, Kubernetes ${K8S_VERSIONS// /, }; 2 HAProxy configurations)"
