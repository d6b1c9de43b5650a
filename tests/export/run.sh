#!/usr/bin/env bash
# Motion export (BVH, C3D, TRC) checked with the real tools.
#
# Adjusts the five examples through a release server on a free loopback port
# (`blapose-client adjust FILE --out --bvh --c3d --trc`, and one `replay`,
# whose lengths change over the stream), then reads every file back with
# readers that are not ours and compares with the adjusted poses
# (check.py): Blender's own BVH importer, headless (blender_import.py; every
# joint by name within 1 mm, the armature's bone lengths within 0.1 mm),
# ezc3d and py-c3d for C3D and OpenSim's TRCFileAdapter for TRC (within
# 0.01 mm), and Python's blapose.export against the Rust writer. It also
# checks the client's errors (an unwritable path, non-finite poses, a file
# with no poses) and renders one frame of the walk to a PNG.
#
# Needs: Debian's blender (installed here when missing; needs root), the
# release binaries (built here), a Python with the blapose package:
# $BLAPOSE_PYTHON, default the venv .ci/run creates (target/pyvenv-ci); ezc3d,
# c3d and opensim are pip-installed into it when missing.
# $BLAPOSE_EXPORT_DIR keeps the files and the PNG (default: a temporary
# directory, removed).
set -euo pipefail
cd "$(dirname "$0")/../.."
# shellcheck source=../e2e-lib.sh
. tests/e2e-lib.sh
ROOT=$PWD
PY=${BLAPOSE_PYTHON:-$ROOT/target/pyvenv-ci/bin/python}

if ! command -v blender >/dev/null; then
    echo "== installing Debian's blender"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq blender >/dev/null
fi
if [ ! -x "$PY" ]; then
    echo "error: $PY not found: run .ci/run, or set BLAPOSE_PYTHON to a Python with './python' installed" >&2
    exit 1
fi
if ! "$PY" -c "import ezc3d, c3d, opensim" 2>/dev/null; then
    echo "== pip install ezc3d c3d opensim (independent C3D and TRC readers)"
    "$PY" -m pip install --quiet --disable-pip-version-check ezc3d c3d opensim
fi
build_release -p blapose-server -p blapose-client

use_out_dir "${BLAPOSE_EXPORT_DIR:-}"

start_server "$OUT/server.log"
CLIENT="target/release/blapose-client --server $URL"

echo "== adjust the examples, writing BVH, C3D and TRC (server $URL)"
for f in examples/cmu_*.npz; do
    name=$(basename "$f" .npz)
    $CLIENT adjust "$f" --out "$OUT/$name.npz" --bvh "$OUT/$name.bvh" --c3d "$OUT/$name.c3d" --trc "$OUT/$name.trc" \
        >"$OUT/$name.log"
    ln -sf "$ROOT/$f" "$OUT/$name.src.npz"
    grep -E "BVH|C3D|TRC|rotation|lengths" "$OUT/$name.log" | sed "s/^/   $name: /"
done
# A stream: its lengths change frame by frame, the files use the final ones.
$CLIENT replay examples/cmu_02_02_walk.npz --out "$OUT/stream_walk.npz" --bvh "$OUT/stream_walk.bvh" \
    --c3d "$OUT/stream_walk.c3d" --trc "$OUT/stream_walk.trc" >"$OUT/stream_walk.log"
ln -sf "$ROOT/examples/cmu_02_02_walk.npz" "$OUT/stream_walk.src.npz"
grep -q "re-posed with the final bone lengths" "$OUT/stream_walk.log" || {
    echo "error: replay --bvh did not say which lengths the files use:" >&2; cat "$OUT/stream_walk.log" >&2; exit 1; }

echo "== bad requests get clear errors"
expect_error() {  # expect_error "message part" command...
    local want=$1; shift
    if "$@" >"$OUT/err.log" 2>&1; then echo "error: '$*' succeeded" >&2; exit 1; fi
    grep -q -- "$want" "$OUT/err.log" || { echo "error: '$*' did not say '$want':" >&2; cat "$OUT/err.log" >&2; exit 1; }
    echo "   ok: $(grep -m1 -- "$want" "$OUT/err.log")"
}
expect_error "its directory does not exist" $CLIENT adjust examples/cmu_02_02_walk.npz --bvh /nonexistent-dir/a.bvh
"$PY" - "$OUT" <<'PYEOF'
import sys
import numpy as np
out = sys.argv[1]
d = dict(np.load("examples/cmu_02_02_walk.npz"))
d["pose_3d"] = d["pose_3d"].copy()
d["pose_3d"][5, 3, 1] = np.nan
np.savez(f"{out}/nan.npz", **d)
PYEOF
expect_error "not finite" $CLIENT adjust "$OUT/nan.npz" --bvh "$OUT/nan.bvh"
"$PY" -c "
import numpy as np, sys
np.savez(sys.argv[1], keypoints_2d=np.zeros((0, 17, 2), np.float32), pose_3d=np.zeros((0, 17, 3), np.float32),
         image_size=np.array([1000, 1000], np.float32))" "$OUT/empty.npz"
expect_error "no frames" $CLIENT adjust "$OUT/empty.npz" --bvh "$OUT/empty.bvh"

echo "== Blender $(blender --version 2>/dev/null | head -n 1 | cut -d' ' -f2): import every BVH, render one frame"
"$PY" tests/export/check.py blender-job "$OUT" "$OUT/job.json"
blender -b --factory-startup -P tests/export/blender_import.py -- "$OUT/job.json" >"$OUT/blender.log" 2>&1 || {
    echo "error: blender failed:" >&2; tail -n 30 "$OUT/blender.log" >&2; exit 1; }
grep "blender_import:" "$OUT/blender.log"
ls -l "$OUT/walk.png" | awk '{print "   " $5 " bytes  " $NF}'

echo "== compare with the adjusted poses"
"$PY" tests/export/check.py verify "$OUT" "$OUT/blender.json"

echo "== the motion stage: the walk moves through space in Blender (adjust and replay --camera --motion)"
mkdir -p "$OUT/motion"
$CLIENT adjust examples/cmu_02_02_walk.npz --camera --motion --out "$OUT/motion/walk.npz" \
    --bvh "$OUT/motion/walk.bvh" >"$OUT/motion/walk.log"
$CLIENT replay examples/cmu_02_02_walk.npz --camera --motion --out "$OUT/motion/stream_walk.npz" \
    --bvh "$OUT/motion/stream_walk.bvh" >"$OUT/motion/stream_walk.log"
for log in walk stream_walk; do
    grep -q "exports in world coordinates" "$OUT/motion/$log.log" || {
        echo "error: $log: the exports are not in world coordinates:" >&2; cat "$OUT/motion/$log.log" >&2; exit 1; }
    grep -E "motion:|world" "$OUT/motion/$log.log" | sed "s/^/   $log: /"
done
"$PY" tests/export/check.py motion-job "$OUT/motion" "$OUT/motion/job.json"
blender -b --factory-startup -P tests/export/blender_import.py -- "$OUT/motion/job.json" >"$OUT/motion/blender.log" 2>&1 || {
    echo "error: blender failed:" >&2; tail -n 30 "$OUT/motion/blender.log" >&2; exit 1; }
"$PY" tests/export/check.py walks "$OUT/motion" "$OUT/motion/blender.json"
