#!/usr/bin/env python3
"""Check exported files against the adjusted poses they were written from, with readers
that are not ours: Blender's BVH importer (its output, from blender_import.py), ezc3d and
py-c3d for C3D, OpenSim's TRCFileAdapter for TRC.

    check.py blender-job OUT_DIR JOB.json        # write Blender's job for OUT_DIR's files
    check.py verify OUT_DIR BLENDER.json         # compare everything, print the numbers
    check.py motion-job DIR JOB.json             # Blender's job for DIR/walk.bvh (adjust --motion)
    check.py walks DIR BLENDER.json              # the placed walk travels and keeps its feet down

OUT_DIR holds, per example NAME: NAME.npz (the client's --out: adjusted_3d, bone_lengths),
NAME.src.npz (a link to the input: fps, camera_up), NAME.bvh, NAME.c3d, NAME.trc. The
expected positions are the documented axis change of ``adjusted_3d``: Blender's world and
the C3D/TRC frame are the Z-up frame (metres in Blender, millimetres in the files).
"""

import json
import sys
import warnings
from pathlib import Path

import numpy as np

import blapose
from blapose import export

JOINTS = list(blapose.JOINT_NAMES)
PARENTS = blapose.PARENTS
BLENDER_TOL_M = 1e-3  # 1 mm
LENGTH_TOL_M = 1e-4  # 0.1 mm
MARKER_TOL_MM = 1e-2  # 0.01 mm


def expected(out: Path, name: str):
    """(Z-up positions in metres (T, 17, 3), lengths (16,), fps) of NAME's export."""
    adj = np.load(out / f"{name}.npz")
    src = np.load(out / f"{name}.src.npz")
    up = src["camera_up"] if "camera_up" in src else None
    # The documented frame, written out here independently of blapose.export:
    # Y = up, Z = level -z (or -y when up is near +-z), X = Y x Z; Z-up = (X, -Z, Y).
    u = np.array((0, -1, 0) if up is None else up, float)
    y = u / np.linalg.norm(u)
    back = np.array((0.0, -1.0, 0.0)) if abs(y[2]) > np.sqrt(0.5) else np.array((0.0, 0.0, -1.0))
    z = back - y * (back @ y)
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    zup = np.stack([x, -z, y])
    lengths = adj["bone_lengths"][-1].astype(float)
    poses = adj["adjusted_3d"].astype(float)
    # The export re-poses every frame with the final lengths (a no-op for adjust).
    reposed = blapose.export.repose(poses, lengths)[0].astype(float)
    fps = float(src["fps"].reshape(-1)[0]) if "fps" in src else 50.0
    return reposed @ zup.T, poses @ zup.T, lengths, fps


def names(out: Path):
    return sorted(p.name[: -len(".bvh")] for p in out.glob("*.bvh") if (out / (p.stem + ".npz")).exists())


def sampled(T: int):
    """Every frame of a short example (at most 200, evenly spread, the last included)."""
    return sorted(set(np.linspace(0, T - 1, min(T, 200)).round().astype(int).tolist()))


def blender_job(out: Path, job: Path):
    files = []
    for name in names(out):
        T = len(np.load(out / f"{name}.npz")["adjusted_3d"])
        files.append({"bvh": str(out / f"{name}.bvh"), "frames": sampled(T)})
    walk = next((f for f in files if "walk" in f["bvh"]), files[0])
    job.write_text(json.dumps({
        "files": files,
        "render": {"bvh": walk["bvh"], "frame": walk["frames"][2], "png": str(out / "walk.png")},
        "out": str(out / "blender.json"),
    }))


def check_blender(out: Path, name: str, result: dict, failures: list):
    want, raw, lengths, fps = expected(out, name)
    got = result[str(out / f"{name}.bvh")]
    worst = worst_raw = 0.0
    for i, heads in got["frames"].items():
        for j, joint in enumerate(JOINTS):
            worst = max(worst, float(np.linalg.norm(np.array(heads[joint]) - want[int(i), j])))
            worst_raw = max(worst_raw, float(np.linalg.norm(np.array(heads[joint]) - raw[int(i), j])))
    # After `adjust` the lengths are constant: the files reproduce adjusted_3d itself.
    constant = np.ptp(np.load(out / f"{name}.npz")["bone_lengths"], axis=0).max() == 0
    if constant and worst_raw >= BLENDER_TOL_M:
        failures.append(f"blender {name}: {worst_raw} m from adjusted_3d as written")
    rest = got["rest"]
    worst_len = 0.0
    for b in range(16):
        p, c = JOINTS[PARENTS[b + 1]], JOINTS[b + 1]
        d = np.linalg.norm(np.array(rest[c]["head"]) - np.array(rest[p]["head"]))
        worst_len = max(worst_len, abs(d - lengths[b]))
    # Bones with one child: Blender's own bone length is the sequence's length.
    single = {"r_hip": 1, "r_knee": 2, "l_hip": 4, "l_knee": 5, "spine": 7, "neck_nose": 9, "l_shoulder": 11,
              "l_elbow": 12, "r_shoulder": 14, "r_elbow": 15, "r_pelvis": 0, "l_pelvis": 3, "l_clavicle": 10,
              "r_clavicle": 13}
    for bone, b in single.items():
        r = rest[bone]
        worst_len = max(worst_len, abs(np.linalg.norm(np.array(r["tail"]) - np.array(r["head"])) - lengths[b]))
    ok = worst < BLENDER_TOL_M and worst_len < LENGTH_TOL_M and abs(got["fps"] - fps) < 1e-6
    what = f"(adjusted_3d itself: {1000 * worst_raw:.4f} mm)" if constant else "(re-posed with the final lengths)"
    print(f"  blender  {name}: {len(got['frames'])} frames x 17 joints within {1000 * worst:.4f} mm {what}, "
          f"bone lengths within {1000 * worst_len:.5f} mm, scene fps {got['fps']:g}")
    if not ok:
        failures.append(f"blender {name}: joints {worst} m, lengths {worst_len} m, fps {got['fps']} vs {fps}")


def check_c3d(out: Path, name: str, failures: list):
    import c3d as pyc3d
    import ezc3d

    want_m, _, _, fps = expected(out, name)
    want = want_m * 1000.0
    c = ezc3d.c3d(str(out / f"{name}.c3d"))
    labels = c["parameters"]["POINT"]["LABELS"]["value"]
    pts = c["data"]["points"]  # (4, points, frames)
    idx = [labels.index(j) for j in JOINTS]
    ez = np.transpose(pts[:3, idx, :], (2, 1, 0))
    units = c["parameters"]["POINT"]["UNITS"]["value"][0]
    rate = c["parameters"]["POINT"]["RATE"]["value"][0]
    e1 = float(np.abs(ez - want).max())
    with open(out / f"{name}.c3d", "rb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "No analog data found in file": there is none
        r = pyc3d.Reader(f)
        plabels = [s.strip() for s in r.point_labels]
        frames = np.stack([p[:, :3] for _, p, _ in r.read_frames()])
        pidx = [plabels.index(j) for j in JOINTS]
        e2 = float(np.abs(frames[:, pidx] - want).max())
        prate = r.point_rate
    ok = max(e1, e2) < MARKER_TOL_MM and units == "mm" and abs(rate - fps) < 1e-4 and abs(prate - fps) < 1e-4
    print(f"  c3d      {name}: ezc3d within {e1:.5f} mm, py-c3d within {e2:.5f} mm ({len(ez)} frames, {units}, {rate:g} Hz)")
    if not ok:
        failures.append(f"c3d {name}: ezc3d {e1} mm, c3d {e2} mm, units {units}, rate {rate}/{prate} vs {fps}")


def check_trc(out: Path, name: str, failures: list):
    import opensim

    want_m, _, _, fps = expected(out, name)
    want = want_m * 1000.0
    table = opensim.TimeSeriesTableVec3(str(out / f"{name}.trc"))  # reads through TRCFileAdapter
    labels = list(table.getColumnLabels())
    T = table.getNumRows()
    got = np.zeros((T, 17, 3))
    for j, joint in enumerate(JOINTS):
        col = table.getDependentColumnAtIndex(labels.index(joint))
        for t in range(T):
            v = col[t]
            got[t, j] = (v.get(0), v.get(1), v.get(2))
    err = float(np.abs(got - want).max())
    units = table.getTableMetaDataAsString("Units")
    rate = float(table.getTableMetaDataAsString("DataRate"))
    times = np.array(table.getIndependentColumn())
    ok = err < MARKER_TOL_MM and units == "mm" and abs(rate - fps) < 1e-4 and abs(times[1] - 1 / fps) < 1e-6
    print(f"  trc      {name}: OpenSim TRCFileAdapter within {err:.5f} mm ({T} frames, {units}, {rate:g} Hz)")
    if not ok:
        failures.append(f"trc {name}: {err} mm, units {units}, rate {rate} vs {fps}")


def check_python_writers(out: Path, name: str, failures: list):
    """blapose.export (Python) writes what the Rust writer wrote, up to float rounding."""
    adj = np.load(out / f"{name}.npz")
    src = np.load(out / f"{name}.src.npz")
    up = src["camera_up"] if "camera_up" in src else None
    fps = float(src["fps"].reshape(-1)[0]) if "fps" in src else 50.0
    text, report = export.bvh_text(adj["adjusted_3d"], adj["bone_lengths"], fps=fps, up=up)
    rust = (out / f"{name}.bvh").read_text()
    head_py, body_py = text.split("MOTION\n")
    head_rs, body_rs = rust.split("MOTION\n")
    a = np.array([[float(v) for v in l.split()] for l in body_py.splitlines()[2:]])
    b = np.array([[float(v) for v in l.split()] for l in body_rs.splitlines()[2:]])
    d = float(np.abs(a - b).max())
    c3d_py = np.frombuffer(export.c3d_bytes(adj["adjusted_3d"], adj["bone_lengths"], fps=fps, up=up), np.uint8)
    c3d_rs = np.fromfile(out / f"{name}.c3d", np.uint8)
    same_layout = len(c3d_py) == len(c3d_rs)
    start = 512 * (int.from_bytes(bytes(c3d_rs[16:18]), "little") - 1)
    dc = float(np.abs(c3d_py[start:].view("<f4") - c3d_rs[start:].view("<f4")).max()) if same_layout else np.inf
    ok = head_py == head_rs and d < 2e-5 and same_layout and (c3d_py[:start] == c3d_rs[:start]).all() and dc < 1e-3
    print(f"  python   {name}: same hierarchy, channels within {d:.1e}, C3D header identical, data within {dc:.1e} mm; "
          f"largest frame-to-frame rotation {report.max_step_deg:.1f} deg ({report.max_step_joint})")
    if not ok:
        failures.append(f"python writers {name}: hierarchy same {head_py == head_rs}, channels {d}, c3d {dc}")


# The placed walks: offline (adjust --motion: feet held) and streamed (replay --motion:
# causal, feet not held: only its travel is asserted, its stance printed).
WALK_FILES = (("walk", True), ("stream_walk", False))


def motion_job(out: Path, job: Path):
    job.write_text(json.dumps({
        "files": [{"bvh": str(out / f"{name}.bvh"), "frames": list(range(len(np.load(out / f"{name}.npz")["adjusted_3d"])))}
                  for name, _ in WALK_FILES],
        "out": str(out / "blender.json"),
    }))  # fmt: skip


# The capture walks 4.0 m; the placed pelvis must travel 3-5 m in Blender.
WALK_M = (3.0, 5.0)
# An ankle slower than this (m/s) for at least STANCE_FRAMES frames is planted; within
# each such run it must not slide more than STANCE_SLIDE_M per frame along the floor. Its
# height within a run is printed, not asserted: measured 39-52 mm on the walk, short of
# "feet on the floor" (the server holds fewer frames than this definition counts).
STANCE_SPEED = 0.3
STANCE_FRAMES = 5
STANCE_SLIDE_M = 0.01
# Where a planted ankle may stand above the floor in world coordinates (m).
FLOOR_BAND_M = (-0.03, 0.15)


def stance_runs(slow):
    """(start, end) of each run of at least STANCE_FRAMES True values."""
    runs, start = [], None
    for i, v in enumerate(list(slow) + [False]):
        if v and start is None:
            start = i
        elif not v and start is not None:
            if i - start >= STANCE_FRAMES:
                runs.append((start, i))
            start = None
    return runs


def walks(out: Path, blender_json: Path):
    failures = []
    for name, feet_held in WALK_FILES:
        failures += [f"{name}: {f}" for f in walk(out, blender_json, name, feet_held)]
    for f in failures:
        print(f"FAILED: {f}")
    return 1 if failures else 0


def walk(out: Path, blender_json: Path, name: str, feet_held: bool):
    """What fails in one placed walk's BVH as Blender read it."""
    got = json.loads(blender_json.read_text())[str(out / f"{name}.bvh")]
    fps = got["fps"]
    frames = sorted(got["frames"], key=int)
    heads = lambda joint: np.array([got["frames"][i][joint] for i in frames])  # noqa: E731
    pelvis = heads(JOINTS[0])
    travel = float(np.linalg.norm(pelvis[-1, :2] - pelvis[0, :2]))
    failures = []
    if not WALK_M[0] <= travel <= WALK_M[1]:
        failures.append(f"the pelvis travels {travel:.2f} m, not {WALK_M[0]}-{WALK_M[1]} m")
    print(f"motion ({name}): the pelvis travels {travel:.2f} m in Blender (the capture walks 4.0 m)")
    for joint in ("r_ankle", "l_ankle"):
        a = heads(joint)
        speed = np.linalg.norm(np.diff(a[:, :2], axis=0), axis=1) * fps
        runs = stance_runs(speed < STANCE_SPEED)
        if not runs:
            print(f"motion ({name}): {joint} never slower than {STANCE_SPEED} m/s for {STANCE_FRAMES} frames")
            if feet_held:
                failures.append(f"{joint}: never planted")
            continue
        # Frame k of `speed` is the step into frame k + 1 of `a`.
        height = max(float(np.ptp(a[s + 1:e + 1, 2])) for s, e in runs)
        slide = max(float(np.linalg.norm(np.diff(a[s + 1:e + 1, :2], axis=0), axis=1).max(initial=0))
                    for s, e in runs)
        plants = [float(np.median(a[s + 1:e + 1, 2])) for s, e in runs]
        floor = float(np.ptp(plants))
        print(f"motion ({name}): {joint} planted {len(runs)} times; within a plant it moves at most "
              f"{1000 * height:.1f} mm up or down and {1000 * slide:.1f} mm per frame along the floor; "
              f"the plants' heights differ by {1000 * floor:.0f} mm (depth error)")
        if feet_held and slide > STANCE_SLIDE_M:
            failures.append(f"{joint}: a planted foot slides {slide:.3f} m per frame")
        # The walk's calibration has a camera height: the files are in world coordinates,
        # so a planted ankle stands on the floor (an ankle is about 70 mm above it).
        print(f"motion ({name}): {joint}'s plants stand {', '.join(f'{1000 * h:.0f}' for h in plants)} mm "
              "above the floor")  # fmt: skip
        if feet_held and not all(FLOOR_BAND_M[0] <= h <= FLOOR_BAND_M[1] for h in plants):
            failures.append(f"{joint}: planted at {plants} m, not on the floor")
    return failures


def verify(out: Path, blender_json: Path):
    result = json.loads(blender_json.read_text())
    failures: list = []
    for name in names(out):
        check_blender(out, name, result, failures)
        check_c3d(out, name, failures)
        check_trc(out, name, failures)
        check_python_writers(out, name, failures)
    n = 4 * len(names(out))
    print(f"export: {n - len(failures)} passed, {len(failures)} failed")
    for f in failures:
        print(f"FAILED: {f}")
    return 1 if failures else 0


if __name__ == "__main__":
    cmd, out = sys.argv[1], Path(sys.argv[2]).resolve()
    if cmd == "blender-job":
        blender_job(out, Path(sys.argv[3]))
    elif cmd == "motion-job":
        motion_job(out, Path(sys.argv[3]))
    elif cmd == "walks":
        sys.exit(walks(out, Path(sys.argv[3])))
    else:
        sys.exit(verify(out, Path(sys.argv[3])))
