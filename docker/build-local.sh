#!/usr/bin/env bash
# Build the blapose-server image without Docker Hub.
#
# Uses whichever container engine is present (podman preferred, else docker
# with a running daemon; on Debian/Ubuntu as root, podman is installed with
# apt when neither is). The Dockerfile's two base images are made locally
# when the engine lacks them:
#
#   debian:bookworm-slim     debootstrap --variant=minbase, imported
#   rust:1.95-slim-bookworm  that + this machine's Rust toolchain (from
#                            `rustc --print sysroot`, docs left out) + gcc
#                            (apt) + this machine's CA bundle, so cargo
#                            reaches the crate registry from the build
#
# debootstrap fetches from the Debian mirror this machine's apt already uses
# (the first http(s) URI of a Debian release with the main component in
# /etc/apt/sources.list, then /etc/apt/sources.list.d/*.list and *.sources),
# unless --mirror or BLAPOSE_DEBIAN_MIRROR names one.
#
# then builds docker/Dockerfile with them as --build-args and prints the
# image size and the build time. The build uses the host network (cargo and
# apt fetch from inside it).
#
#   docker/build-local.sh                 # build blapose-server:latest
#   docker/build-local.sh --tag blapose-server:dev --engine docker
#   docker/smoke-test.sh                  # then test it
#
# Run from anywhere; the build context is the repository root.
set -euo pipefail

usage() {
    cat <<'EOF'
Usage: docker/build-local.sh [OPTIONS]

Build the blapose-server image from local base images (no Docker Hub needed).

Options:
  --engine NAME         podman or docker (default: podman if installed, else
                        docker if its daemon answers, else install podman)
  --tag TAG             image to build (default: blapose-server:latest)
  --rust-image NAME     build-stage base (default: rust:1.95-slim-bookworm,
                        or rust:<host rustc major.minor>-slim-<suite>)
  --debian-image NAME   base of the rust image (default: debian:<suite>-slim)
  --runtime-image NAME  runtime base passed as RUNTIME_IMAGE (default: the
                        Dockerfile's, scratch)
  --suite NAME          Debian release for debootstrap (default: bookworm)
  --mirror URL          Debian mirror for debootstrap (default:
                        $BLAPOSE_DEBIAN_MIRROR, else the first http(s) URI
                        of a Debian release with the main component in this
                        machine's apt sources: /etc/apt/sources.list, then
                        /etc/apt/sources.list.d/*.list and *.sources)
  --print-mirror        print the mirror debootstrap would use and exit
  --no-bases            never create base images (the engine pulls missing
                        ones, e.g. from Docker Hub)
  --rebuild-bases       recreate both base images even if present
  --no-install          never apt-get install podman/runc/debootstrap
  --no-cache            build without the engine's layer cache
  --json PATH           also write {"image","engine","size_mb","build_s"}
  -h, --help            show this help

On a shared machine prefix it with `nice -n 19` (the engine's build
processes inherit the niceness with podman; not with docker's daemon).
EOF
}

log() { printf '==> %s\n' "$*" >&2; }
die() { printf 'build-local.sh: error: %s\n' "$*" >&2; exit 1; }

repo_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)

engine=""
tag="blapose-server:latest"
suite="bookworm"
mirror=${BLAPOSE_DEBIAN_MIRROR:-}
print_mirror=0
rust_image=""
debian_image=""
runtime_image=""
make_bases=1
rebuild_bases=0
may_install=1
no_cache=0
json_out=""

while [[ $# -gt 0 ]]; do
    case "$1" in
        --engine) engine=${2:?--engine needs a value}; shift 2 ;;
        --tag) tag=${2:?--tag needs a value}; shift 2 ;;
        --rust-image) rust_image=${2:?--rust-image needs a value}; shift 2 ;;
        --debian-image) debian_image=${2:?--debian-image needs a value}; shift 2 ;;
        --runtime-image) runtime_image=${2:?--runtime-image needs a value}; shift 2 ;;
        --suite) suite=${2:?--suite needs a value}; shift 2 ;;
        --mirror) mirror=${2:?--mirror needs a value}; shift 2 ;;
        --print-mirror) print_mirror=1; shift ;;
        --no-bases) make_bases=0; shift ;;
        --rebuild-bases) rebuild_bases=1; shift ;;
        --no-install) may_install=0; shift ;;
        --no-cache) no_cache=1; shift ;;
        --json) json_out=${2:?--json needs a path}; shift 2 ;;
        -h|--help) usage; exit 0 ;;
        *) usage >&2; die "unknown option: $1" ;;
    esac
done

debian_image=${debian_image:-debian:${suite}-slim}

# --- helpers -----------------------------------------------------------------

have() { command -v "$1" >/dev/null 2>&1; }

apt_install() {
    [[ $may_install -eq 1 ]] || die "missing $*; install it (or drop --no-install)"
    have apt-get || die "missing $*, and no apt-get to install it with"
    [[ $(id -u) -eq 0 ]] || die "missing $*; installing needs root (sudo apt-get install $*)"
    log "installing $* (apt)"
    DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends "$@" >/dev/null \
        || { apt-get update >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends "$@" >/dev/null; } \
        || die "apt-get install $* failed"
}

# The Debian mirror this machine's apt uses: candidates are enabled `deb`
# sources (not deb-src) with the `main` component, an http(s) URI and a Debian
# release as suite (a codename or stable/testing/unstable/oldstable, without a
# -security/-updates/-backports suffix). Files are read in apt's order
# (sources.list, then sources.list.d/ alphabetically; one-line *.list and
# deb822 *.sources). Among the candidates the first wins whose suite is the
# one being built and whose path ends in /debian, else the first with that
# suite, else the first whose path ends in /debian, else the first at all.
# Prints the URI without a trailing slash; fails when there is none.
detect_debian_mirror() {
    local etc=${1:-/etc/apt} want=${2:-$suite}
    # apt's order: sources.list, then sources.list.d/ by name.
    local files=() f
    [[ -f $etc/sources.list ]] && files+=("$etc/sources.list")
    for f in "$etc"/sources.list.d/*; do
        [[ -f $f && ( $f == *.list || $f == *.sources ) ]] && files+=("$f")
    done
    [[ ${#files[@]} -gt 0 ]] || return 1
    local best
    best=$(
        for f in "${files[@]}"; do
            if [[ $f == *.sources ]]; then
                awk -v want="$want" -f <(mirror_awk_common; cat <<'AWK'
function flush() {
    if (types != "" && enabled !~ /^[Nn][Oo]$/) consider(types, uris, suites, comps)
    types = ""; uris = ""; suites = ""; comps = ""; enabled = ""; key = ""
}
/^[ \t]*#/ { next }
/^[ \t]*$/ { flush(); next }
/^[ \t]/ {
    line = $0; sub(/^[ \t]+/, "", line)
    if (key == "types") types = types " " line
    else if (key == "uris") uris = uris " " line
    else if (key == "suites") suites = suites " " line
    else if (key == "components") comps = comps " " line
    next
}
{
    i = index($0, ":"); if (i == 0) next
    key = tolower(substr($0, 1, i - 1)); val = substr($0, i + 1)
    sub(/[ \t]+#.*$/, "", val)
    if (key == "types") types = val
    else if (key == "uris") uris = val
    else if (key == "suites") suites = val
    else if (key == "components") comps = val
    else if (key == "enabled") { enabled = val; gsub(/[ \t]/, "", enabled) }
}
END { flush() }
AWK
                ) "$f"
            else
                awk -v want="$want" -f <(mirror_awk_common; cat <<'AWK'
/^[ \t]*#/ { next }
{
    line = $0
    sub(/#.*$/, "", line)
    gsub(/\[[^]]*\]/, " ", line)
    n = split(line, w, /[ \t]+/)
    j = 1; while (j <= n && w[j] == "") j++
    if (w[j] != "deb" || j + 3 > n) next
    comps = ""
    for (k = j + 3; k <= n; k++) comps = comps " " w[k]
    consider("deb", w[j + 1], w[j + 2], comps)
}
AWK
                ) "$f"
            fi
        done | LC_ALL=C sort -s -n -k1,1 | head -n 1
    )
    [[ -n $best ]] || return 1
    printf '%s\n' "${best#* }"
}

# awk helpers shared by both source formats: consider() prints "RANK URI"
# for each http(s) URI of an entry that is a Debian main repository.
mirror_awk_common() {
    cat <<'AWK'
function has_word(list, word,    a, n, i) {
    n = split(list, a, /[ \t]+/)
    for (i = 1; i <= n; i++) if (a[i] == word) return 1
    return 0
}
function consider(types, uris, suites, comps,    s, ns, i, u, nu, j, rank, r, uri) {
    if (!has_word(types, "deb") || !has_word(comps, "main")) return
    rank = -1
    ns = split(suites, s, /[ \t]+/)
    for (i = 1; i <= ns; i++) {
        if (s[i] == "") continue
        if (s[i] !~ /^(buzz|rex|bo|hamm|slink|potato|woody|sarge|etch|lenny|squeeze|wheezy|jessie|stretch|buster|bullseye|bookworm|trixie|forky|duke|sid|stable|testing|unstable|oldstable|oldoldstable)$/) continue
        r = (s[i] == want) ? 0 : 1
        if (rank < 0 || r < rank) rank = r
    }
    if (rank < 0) return
    nu = split(uris, u, /[ \t]+/)
    for (j = 1; j <= nu; j++) {
        uri = u[j]
        if (uri !~ /^https?:\/\/[^\/]/) continue
        sub(/\/+$/, "", uri)
        # 0: wanted suite, path .../debian; 1: wanted suite; 2: other
        # release, path .../debian; 3: other release.
        printf "%d %s\n", rank * 2 + (uri ~ /\/debian$/ ? 0 : 1), uri
        return
    }
}
AWK
}

# The mirror for debootstrap: --mirror, else $BLAPOSE_DEBIAN_MIRROR, else the
# one this machine's apt uses.
resolve_mirror() {
    [[ -n $mirror ]] && return 0
    mirror=$(detect_debian_mirror /etc/apt "$suite") || die "no Debian mirror found: none of /etc/apt/sources.list, /etc/apt/sources.list.d/*.list or *.sources names an http(s) Debian repository with the main component; pass --mirror URL or set BLAPOSE_DEBIAN_MIRROR"
}

docker_has_daemon() { have docker && docker info >/dev/null 2>&1; }

pick_engine() {
    if [[ -n $engine ]]; then
        case "$engine" in
            podman) have podman || apt_install podman runc ;;
            docker) docker_has_daemon || die "docker has no daemon to talk to (try --engine podman)" ;;
            *) die "unsupported engine: $engine (podman or docker)" ;;
        esac
    elif have podman; then
        engine=podman
    elif docker_has_daemon; then
        engine=docker
    else
        log "no container engine (docker here is $(have docker && echo 'a client without a daemon' || echo 'absent')); using podman"
        apt_install podman runc
        engine=podman
    fi
}

image_exists() {
    if [[ $engine == podman ]]; then podman image exists "$1"
    else docker image inspect "$1" >/dev/null 2>&1; fi
}

# podman as root asks for RLIMIT_NOFILE=1048576 in every container; where
# the hard limit is lower (containers, CI runners) every RUN step fails with
# "setrlimit ... operation not permitted". An empty default_ulimits list makes
# containers inherit the engine's own limits. Written only when a probe run
# fails that way, and only once.
ensure_podman_ulimits() {
    [[ $engine == podman ]] || return 0
    local probe out conf=/etc/containers/containers.conf
    probe=$1
    if out=$(podman run --rm --network host "$probe" true 2>&1); then return 0; fi
    if ! grep -qiE 'rlimit|ulimit' <<<"$out"; then
        printf '%s\n' "$out" >&2
        die "podman cannot run a container (see above)"
    fi
    [[ $(id -u) -eq 0 ]] || die "podman: $out (set default_ulimits = [] under [containers] in ~/.config/containers/containers.conf)"
    if grep -qE '^\s*default_ulimits\s*=' "$conf" 2>/dev/null; then
        printf '%s\n' "$out" >&2
        die "podman fails on ulimits although $conf sets default_ulimits; check that setting"
    fi
    log "podman: containers ask for more open files than allowed here; setting default_ulimits = [] in $conf"
    mkdir -p "$(dirname "$conf")"
    if grep -qE '^\s*\[containers\]' "$conf" 2>/dev/null; then
        sed -i '0,/^\s*\[containers\]/s//[containers]\ndefault_ulimits = []/' "$conf"
    else
        printf '\n[containers]\ndefault_ulimits = []\n' >>"$conf"
    fi
    podman run --rm --network host "$probe" true || die "podman still cannot run a container"
}

image_size_bytes() {
    "$engine" image inspect --format '{{.Size}}' "$1"
}

# --- base images -------------------------------------------------------------

make_debian_image() {
    have debootstrap || apt_install debootstrap
    local dir started
    resolve_mirror
    dir=$(mktemp -d /tmp/blapose-rootfs.XXXXXX)
    started=$(date +%s)
    log "debootstrap --variant=minbase $suite $mirror -> $debian_image (a few minutes)"
    debootstrap --variant=minbase "$suite" "$dir" "$mirror" >/tmp/blapose-debootstrap.log 2>&1 \
        || { tail -20 /tmp/blapose-debootstrap.log >&2; rm -rf "$dir"; die "debootstrap failed (log: /tmp/blapose-debootstrap.log)"; }
    # What the official slim images drop: apt caches and package lists
    # (every Dockerfile runs apt-get update first anyway).
    rm -rf "$dir"/var/cache/apt/*.bin "$dir"/var/cache/apt/archives/*.deb "$dir"/var/lib/apt/lists/*
    tar -C "$dir" --numeric-owner -cf - . \
        | "$engine" import --change 'CMD ["/bin/bash"]' - "$debian_image" >>/tmp/blapose-debootstrap.log 2>&1 \
        || { tail -5 /tmp/blapose-debootstrap.log >&2; rm -rf "$dir"; die "import of $debian_image failed"; }
    rm -rf "$dir"
    log "$debian_image made in $(( $(date +%s) - started )) s"
}

make_rust_image() {
    local sysroot ctx started
    have rustc || die "no rustc on this machine to copy into $rust_image (install rustup, or pass --rust-image with an existing image)"
    sysroot=$(rustc --print sysroot)
    [[ -x $sysroot/bin/cargo ]] || die "no cargo next to rustc in $sysroot"
    local ca=/etc/ssl/certs/ca-certificates.crt
    [[ -r $ca ]] || die "no CA bundle at $ca (cargo in the build needs it to reach the crate registry)"
    ctx=$(mktemp -d /tmp/blapose-rust-ctx.XXXXXX)
    started=$(date +%s)
    log "$rust_image: $debian_image + $(rustc --version) from $sysroot + gcc + CA bundle"
    mkdir -p "$ctx/toolchain"
    # Everything but share/ (docs, ~800 MB); hard links where possible.
    local part
    for part in bin lib libexec etc; do
        [[ -e $sysroot/$part ]] || continue
        cp -al "$sysroot/$part" "$ctx/toolchain/" 2>/dev/null || cp -a "$sysroot/$part" "$ctx/toolchain/"
    done
    rm -rf "$ctx/toolchain/lib/rustlib/src" "$ctx/toolchain/lib/rustlib/etc"
    cp "$ca" "$ctx/ca-certificates.crt"
    cat >"$ctx/Dockerfile" <<EOF
FROM $debian_image
RUN apt-get update \\
 && apt-get install -y --no-install-recommends gcc libc6-dev \\
 && rm -rf /var/lib/apt/lists/*
COPY ca-certificates.crt /etc/ssl/certs/ca-certificates.crt
COPY toolchain/ /usr/local/rust/
ENV CARGO_HOME=/usr/local/cargo \\
    SSL_CERT_FILE=/etc/ssl/certs/ca-certificates.crt \\
    PATH=/usr/local/cargo/bin:/usr/local/rust/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \\
    RUST_VERSION=$(rustc --version | awk '{print $2}')
RUN mkdir -p /usr/local/cargo/bin && rustc --version && cargo --version
EOF
    "$engine" build --network host -t "$rust_image" "$ctx" >/tmp/blapose-rust-image.log 2>&1 \
        || { tail -30 /tmp/blapose-rust-image.log >&2; rm -rf "$ctx"; die "building $rust_image failed (log: /tmp/blapose-rust-image.log)"; }
    rm -rf "$ctx"
    log "$rust_image made in $(( $(date +%s) - started )) s"
}

ensure_bases() {
    if [[ -z $rust_image ]]; then
        rust_image="rust:1.95-slim-${suite}"
        if have rustc; then
            local v
            v=$(rustc --version | awk '{print $2}' | cut -d. -f1,2)
            rust_image="rust:${v}-slim-${suite}"
        fi
    fi
    if [[ $make_bases -eq 0 ]]; then
        image_exists "$rust_image" || log "$rust_image not present; the engine will try to pull it"
        return 0
    fi
    if [[ $rebuild_bases -eq 1 ]] || ! image_exists "$debian_image"; then
        make_debian_image
    fi
    ensure_podman_ulimits "$debian_image"
    if [[ $rebuild_bases -eq 1 ]] || ! image_exists "$rust_image"; then
        make_rust_image
    fi
}

# --- main --------------------------------------------------------------------

if [[ $print_mirror -eq 1 ]]; then
    resolve_mirror
    printf '%s\n' "$mirror"
    exit 0
fi

pick_engine
log "engine: $("$engine" --version)"
ensure_bases

build_args=(--build-arg "RUST_IMAGE=$rust_image")
[[ -n $runtime_image ]] && build_args+=(--build-arg "RUNTIME_IMAGE=$runtime_image")
# The web stage's npm reads the registry this machine's npm uses (none named
# here: npm's own default where it has none).
npm_registry=$(npm config get registry 2>/dev/null || true)
[[ -n $npm_registry ]] && build_args+=(--build-arg "NPM_CONFIG_REGISTRY=$npm_registry")
engine_args=(--network host -f docker/Dockerfile -t "$tag")
[[ $no_cache -eq 1 ]] && engine_args+=(--no-cache)
if [[ $engine == podman ]]; then
    # HEALTHCHECK survives only in the docker format; podman 4 does not look
    # for <Dockerfile>.dockerignore by itself (BuildKit does).
    engine_args+=(--format docker --ignorefile docker/Dockerfile.dockerignore)
else
    export DOCKER_BUILDKIT=1
fi

log "building $tag ($engine ${engine_args[*]} ${build_args[*]} .)"
started=$(date +%s)
(cd "$repo_root" && "$engine" build "${engine_args[@]}" "${build_args[@]}" .)
build_s=$(( $(date +%s) - started ))

size_bytes=$(image_size_bytes "$tag")
size_mb=$(awk -v b="$size_bytes" 'BEGIN { printf "%.1f", b / 1e6 }')
echo
echo "image:      $tag"
echo "engine:     $("$engine" --version)"
echo "base:       RUST_IMAGE=$rust_image${runtime_image:+ RUNTIME_IMAGE=$runtime_image}"
echo "size:       ${size_mb} MB"
echo "build time: ${build_s} s"
if [[ -n $json_out ]]; then
    printf '{"image":"%s","engine":"%s","size_mb":%s,"build_s":%s}\n' \
        "$tag" "$engine" "$size_mb" "$build_s" >"$json_out"
fi
