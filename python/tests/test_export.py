"""blapose.export: BVH, C3D and TRC writers (numpy only; tests/export/ reads the files
with Blender, ezc3d, py-c3d and OpenSim)."""

import struct
from pathlib import Path

import numpy as np
import pytest

import blapose
from blapose import export

EXAMPLES = sorted((Path(__file__).resolve().parents[2] / "examples").glob("cmu_*.npz"))


def _parse_bvh(text):
    """(names, parents, offsets, per-joint (first channel, has position, order), frames)."""
    names, parents, offsets, chans, stack, in_end, nxt = [], [], [], [], [], False, 0
    head, body = text.split("MOTION\n")
    for line in head.splitlines():
        w = line.split()
        if w[0] in ("ROOT", "JOINT"):
            names.append(w[1])
            parents.append(next((s for s in reversed(stack) if s is not None), None))
        elif w[0] == "End":
            in_end = True
        elif w[0] == "{":
            stack.append(None if in_end else len(names) - 1)
        elif w[0] == "}":
            if stack.pop() is None:
                in_end = False
        elif w[0] == "OFFSET" and not in_end:
            offsets.append(np.array([float(v) for v in w[1:]]))
        elif w[0] == "CHANNELS":
            order = ["XYZ".index(c[0]) for c in w[2:] if c.endswith("rotation")]
            chans.append((nxt, int(w[1]) == 6, order))
            nxt += int(w[1])
    frames = np.array([[float(v) for v in line.split()] for line in body.splitlines()[2:]])
    return names, parents, offsets, chans, frames


def _rot(axis, deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = (axis + 1) % 3, (axis + 2) % 3
    m = np.eye(3)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _fk(parsed, t):
    names, parents, offsets, chans, frames = parsed
    v = frames[t]
    pos, world = {}, {}
    for j, name in enumerate(names):
        c, has_pos, order = chans[j]
        r0 = c + 3 if has_pos else c
        local = _rot(order[0], v[r0]) @ _rot(order[1], v[r0 + 1]) @ _rot(order[2], v[r0 + 2])
        p = parents[j]
        if p is None:
            pos[name], world[name] = offsets[j] + v[c:c + 3], local
        else:
            pos[name] = pos[names[p]] + world[names[p]] @ offsets[j]
            world[name] = world[names[p]] @ local
    return pos


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_bvh_forward_kinematics_gives_back_every_joint(path, tmp_path):
    d = np.load(path)
    poses = d["pose_3d"]
    lengths = np.linalg.norm(poses[:, 1:] - poses[:, list(blapose.PARENTS[1:])], axis=2).mean(0)
    report = export.write_bvh(tmp_path / "a.bvh", poses, lengths, fps=50.0, up=d["camera_up"])
    parsed = _parse_bvh((tmp_path / "a.bvh").read_text())
    assert parsed[0][0] == "pelvis" and set(blapose.JOINT_NAMES) <= set(parsed[0]) and len(parsed[0]) == 21
    reposed, _ = export.repose(poses, lengths)
    y_up, _ = export.export_axes(d["camera_up"])
    want = reposed.astype(float) @ y_up.T
    for t in range(0, len(poses), 7):
        pos = _fk(parsed, t)
        err = max(np.linalg.norm(pos[n] - want[t, j]) for j, n in enumerate(blapose.JOINT_NAMES))
        assert err < 2e-6, (t, err)
    # No half-turn flips: the largest change of any joint's rotation between frames is
    # what 50 Hz motion with 3 degrees of direction noise per bone gives.
    assert report.max_step_deg < 30.0, report
    assert report.max_fk_error_m < 2e-6


def test_rest_pose_and_lengths(tmp_path):
    lengths = np.linspace(0.1, 0.4, 16)
    rest = export._rest_positions(lengths)
    pose = rest * np.array([1.0, -1.0, -1.0])  # camera axes: y down, z away
    text, _ = export.bvh_text(np.stack([pose, pose]), lengths)
    names, parents, offsets, _, frames = _parse_bvh(text)
    assert np.abs(frames).max() < 1e-5  # the rest pose is all zeros
    # zeros as Rust writes them: "0.000000", never "-0.000000"
    assert "-0.000000" not in text.split("MOTION\n")[1]
    world = {}
    for j, n in enumerate(names):
        world[n] = offsets[j] + (world[names[parents[j]]] if parents[j] is not None else 0)
    for b in range(16):
        c, p = blapose.JOINT_NAMES[b + 1], blapose.JOINT_NAMES[blapose.PARENTS[b + 1]]
        assert abs(np.linalg.norm(world[c] - world[p]) - lengths[b]) < 1e-6
    assert text.count("End Site") == 5 and "Frame Time: 0.020000000" in text


def _c3d_points(data: bytes):
    assert data[1] == 0x50 and data[512 + 3] == 84
    npoints, _, first, last = struct.unpack_from("<4H", data, 2)
    scale, start = struct.unpack_from("<fH", data, 12)
    rate = struct.unpack_from("<f", data, 20)[0]
    assert scale < 0 and first == 1
    pts = np.frombuffer(data, "<f4", count=(last - first + 1) * npoints * 4, offset=512 * (start - 1))
    return pts.reshape(-1, npoints, 4), rate


def test_c3d_and_trc_hold_the_markers_in_millimetres_z_up(tmp_path):
    d = np.load(EXAMPLES[0])
    poses, up = d["pose_3d"], d["camera_up"]
    export.write_c3d(tmp_path / "a.c3d", poses, fps=50.0, up=up)
    export.write_trc(tmp_path / "a.trc", poses, fps=50.0, up=up)
    reposed, _ = export.repose(poses)
    _, z_up = export.export_axes(up)
    want = reposed.astype(float) @ z_up.T * 1000.0
    pts, rate = _c3d_points((tmp_path / "a.c3d").read_bytes())
    assert rate == 50.0 and np.abs(pts[..., :3] - want).max() < 1e-3 and not pts[..., 3].any()
    assert (z_up @ (up / np.linalg.norm(up)))[2] == pytest.approx(1.0)
    lines = (tmp_path / "a.trc").read_text().splitlines()
    assert lines[0].endswith("\ta.trc") and lines[2].split("\t")[4] == "mm" and lines[5] == ""
    assert [c for c in lines[3].split("\t") if c][2:] == list(blapose.JOINT_NAMES)
    rows = np.array([[float(v) for v in line.split("\t")] for line in lines[6:]])
    assert rows[1, 1] == pytest.approx(0.02)
    assert np.abs(rows[:, 2:].reshape(-1, 17, 3) - want).max() < 1e-3


def test_lengths_default_and_rows():
    d = np.load(EXAMPLES[0])
    poses = d["pose_3d"]
    _, own = export.repose(poses)
    assert np.allclose(own, np.linalg.norm(poses[-1, 1:] - poses[-1, list(blapose.PARENTS[1:])], axis=1))
    rows = np.tile(np.linspace(0.1, 0.3, 16), (len(poses), 1))
    rows[-1] += 0.01
    reposed, used = export.repose(poses, rows)
    assert np.allclose(used, rows[-1])
    got = np.linalg.norm(reposed[:, 1:] - reposed[:, list(blapose.PARENTS[1:])], axis=2)
    assert np.abs(got - rows[-1]).max() < 1e-5


def test_bad_requests_are_refused_and_nothing_is_written(tmp_path):
    good = np.load(EXAMPLES[0])["pose_3d"]
    with pytest.raises(ValueError, match="no poses"):
        export.write_bvh(tmp_path / "a.bvh", np.zeros((0, 17, 3)))
    bad = good.copy()
    bad[4, 2, 0] = np.inf
    with pytest.raises(ValueError, match=r"frame 4: joint 2 \(r_knee\) has a non-finite coordinate"):
        export.write_c3d(tmp_path / "a.c3d", bad)
    with pytest.raises(ValueError, match="frame rate"):
        export.write_trc(tmp_path / "a.trc", good, fps=0)
    with pytest.raises(ValueError, match="up must be"):
        export.write_bvh(tmp_path / "a.bvh", good, up=(0, 0, 0))
    assert not list(tmp_path.iterdir())
    with pytest.raises(OSError):
        export.write_bvh(tmp_path / "missing-dir" / "a.bvh", good)
