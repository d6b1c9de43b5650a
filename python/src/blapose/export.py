"""Motion export: BVH for animation, C3D and OpenSim TRC for biomechanics (numpy only).

The same files ``blapose-client replay|adjust --bvh/--c3d/--trc`` write (the Rust
``blapose-export`` crate; this is a port of it, checked against it by the tests):

* :func:`write_bvh`: a 21-joint skeleton (the 17 joints by name, plus ``r_pelvis``,
  ``l_pelvis``, ``r_clavicle``, ``l_clavicle`` helpers so that the hips and shoulders can
  move independently), T-pose rest pose with the motion's bone lengths, metres, Y up; per
  frame the pelvis position and every joint's rotation (degrees), whose forward
  kinematics gives back the 17 joints. Twist comes from the hip and shoulder lines and
  the knee and elbow planes (held while a limb is nearly straight), the other joints
  follow their parents with the smallest rotation, so rotations are continuous in time.
* :func:`write_c3d`: 17 points named as the joints, millimetres, Z up, float data.
* :func:`write_trc`: the same markers in OpenSim's tab-separated TRC.

Every function re-poses each frame with ONE set of bone lengths (``lengths``: ``(16,)``,
or ``(T, 16)`` whose last row is used, or None for the last frame's own lengths),
keeping each frame's root and bone directions, so the three formats hold the same
motion. ``up`` is the world's up direction in the poses' coordinates (default
``(0, -1, 0)``: camera axes; a replay file's ``camera.up``). The Y-up frame: ``Y`` = up,
``Z`` = the poses' ``-z`` made level (``-y`` when up is within 45 degrees of ``±z``),
``X = Y × Z``; the Z-up frame is ``(X, -Z, Y)`` of it, what Blender makes of a Y-up BVH.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from .types import BONE_NAMES, JOINT_NAMES, PARENTS

PathLike = Union[str, Path]

_PX, _NX = (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)
_PY, _NY = (0.0, 1.0, 0.0), (0.0, -1.0, 0.0)
_PZ, _NZ = (0.0, 0.0, 1.0), (0.0, 0.0, -1.0)
_ROOT, _VERT, _HORIZ = (1, 0, 2), (2, 1, 0), (2, 0, 1)


def _axis_angle_1(axis: np.ndarray, angle: float) -> np.ndarray:
    x, y, z = axis
    s, c = np.sin(angle), np.cos(angle)
    t = 1.0 - c
    return np.array([[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
                     [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
                     [t * x * z - s * y, t * y * z + s * x, t * z * z + c]])  # fmt: skip

# name, parent, at, aim, rest_dir, order, kind, extra
#   kind "frame": extra = body line ("hips", "shoulders", "both")
#   kind "bend": extra = (far joint, rest bend direction, fold)
#   kind "leaf": extra = End Site direction
RIG = (
    ("pelvis", None, 0, 7, _PY, _ROOT, "frame", "hips"),
    ("r_pelvis", 0, 0, 1, _NX, _HORIZ, "swing", None),
    ("r_hip", 1, 1, 2, _NY, _VERT, "bend", (3, _NZ, True)),
    ("r_knee", 2, 2, 3, _NY, _VERT, "swing", None),
    ("r_ankle", 3, 3, None, _NY, _VERT, "leaf", _PZ),
    ("l_pelvis", 0, 0, 4, _PX, _HORIZ, "swing", None),
    ("l_hip", 5, 4, 5, _NY, _VERT, "bend", (6, _NZ, True)),
    ("l_knee", 6, 5, 6, _NY, _VERT, "swing", None),
    ("l_ankle", 7, 6, None, _NY, _VERT, "leaf", _PZ),
    ("spine", 0, 7, 8, _PY, _VERT, "frame", "both"),
    ("thorax", 9, 8, 9, _PY, _VERT, "frame", "shoulders"),
    ("neck_nose", 10, 9, 10, _PY, _VERT, "swing", None),
    ("head", 11, 10, None, _PY, _VERT, "leaf", _PY),
    ("l_clavicle", 10, 8, 11, _PX, _HORIZ, "swing", None),
    ("l_shoulder", 13, 11, 12, _PX, _HORIZ, "bend", (13, _PZ, False)),
    ("l_elbow", 14, 12, 13, _PX, _HORIZ, "swing", None),
    ("l_wrist", 15, 13, None, _PX, _HORIZ, "leaf", _PX),
    ("r_clavicle", 10, 8, 14, _NX, _HORIZ, "swing", None),
    ("r_shoulder", 17, 14, 15, _NX, _HORIZ, "bend", (16, _PZ, False)),
    ("r_elbow", 18, 15, 16, _NX, _HORIZ, "swing", None),
    ("r_wrist", 19, 16, None, _NX, _HORIZ, "leaf", _NX),
)
#: BVH joint names in file order.
BVH_JOINTS: Tuple[str, ...] = tuple(r[0] for r in RIG)
# The upper arms swing from a neutral pointing forward and out, not from the T-pose's
# sideways direction, so that the swing's singular direction (its opposite, back and
# across the body) is one an arm cannot take: {rig joint: rest -> neutral rotation}.
_NEUTRAL = {
    14: _axis_angle_1(np.array(_PY), -np.pi / 4),
    18: _axis_angle_1(np.array(_PY), np.pi / 4),
}
#: An End Site's length as a fraction of its leaf's bone.
END_SITE_FRACTION = 0.25
#: The knee and elbow planes twist the thigh and upper arm fully from the second bend
#: angle (degrees) on, not at all below the first.
BEND_RAMP_DEG = (15.0, 45.0)


@dataclass(frozen=True)
class BvhReport:
    """What :func:`write_bvh` measured."""

    frames: int
    max_step_deg: float  # largest change of a joint's rotation between two frames
    max_step_joint: str
    max_step_frame: int  # the later of the two frames
    max_fk_error_m: float  # forward kinematics of the written channels vs the positions


# ---------------------------------------------------------------- axes and re-posing


def export_axes(up: Optional[Sequence[float]] = None) -> Tuple[np.ndarray, np.ndarray]:
    """``(y_up, z_up)``: 3x3 matrices whose rows are the export frames' axes in the poses'
    coordinates (``y_up @ p`` is a point in the BVH frame, ``z_up @ p`` in the C3D/TRC frame)."""
    u = np.array((0.0, -1.0, 0.0) if up is None else up, dtype=np.float64).reshape(-1)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or not np.linalg.norm(u) > 1e-12:
        raise ValueError(f"up must be 3 finite values, not all zero, got {up!r}")
    y = u / np.linalg.norm(u)
    back = np.array((0.0, -1.0, 0.0) if abs(y[2]) > np.sqrt(0.5) else (0.0, 0.0, -1.0))
    z = back - y * (back @ y)
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    return np.stack([x, y, z]), np.stack([x, -z, y])


def _check_poses(poses) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float32)
    if p.ndim == 2:
        p = p[None]
    if p.ndim != 3 or p.shape[1:] != (17, 3):
        raise ValueError(f"poses must be (T, 17, 3), got shape {p.shape}")
    if len(p) == 0:
        raise ValueError("nothing to export: the sequence has no poses")
    bad = ~np.isfinite(p).all(axis=2)
    if bad.any():
        t, j = np.argwhere(bad)[0]
        raise ValueError(f"cannot export: frame {t}: joint {j} ({JOINT_NAMES[j]}) has a non-finite coordinate")
    return p


def repose(poses, lengths=None) -> Tuple[np.ndarray, np.ndarray]:
    """``(poses (T, 17, 3) float32, lengths (16,))``: every frame rebuilt with one set of
    lengths, root and bone directions kept (what every writer here exports)."""
    p = _check_poses(poses).astype(np.float64)
    parents = np.array(PARENTS[1:])
    vec = p[:, 1:] - p[:, parents]
    norm = np.linalg.norm(vec, axis=2)
    if lengths is None:
        lengths = norm[-1]
    lengths = np.asarray(lengths, dtype=np.float64)
    if lengths.ndim == 2:
        lengths = lengths[-1]
    lengths = lengths.reshape(-1)
    if lengths.shape != (16,):
        raise ValueError(f"lengths must be (16,) or (T, 16), got shape {np.shape(lengths)}")
    if not (np.all(np.isfinite(lengths)) and np.all(lengths >= 0)):
        b = int(np.argmax(~(np.isfinite(lengths) & (lengths >= 0))))
        raise ValueError(f"cannot export: target length of bone {b} ({BONE_NAMES[b]}) is invalid: {lengths[b]}")
    short = norm < 1e-6
    if short.any():
        t, b = np.argwhere(short)[0]
        raise ValueError(f"cannot export: frame {t}: bone {b} ({BONE_NAMES[b]}) has zero length")
    out = np.empty_like(p)
    out[:, 0] = p[:, 0]
    for j in range(1, 17):
        out[:, j] = out[:, PARENTS[j]] + vec[:, j - 1] * (lengths[j - 1] / norm[:, j - 1])[:, None]
    return out.astype(np.float32), lengths


def _check_fps(fps: float) -> float:
    fps = float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"cannot export: the frame rate must be finite and > 0, got {fps}")
    return fps


# ---------------------------------------------------------------- rotation algebra (vectorized over frames)


def _unit(v: np.ndarray, eps) -> Tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1)
    ok = (n > eps) & np.isfinite(n)
    return v / np.where(ok, n, 1.0)[..., None], ok


def _perp(a, d):
    return a - d * np.sum(a * d, axis=-1, keepdims=True)


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    s, c = np.sin(angle), np.cos(angle)
    t = 1.0 - c
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    return np.stack(
        [
            np.stack([t * x * x + c, t * x * y - s * z, t * x * z + s * y], -1),
            np.stack([t * x * y + s * z, t * y * y + c, t * y * z - s * x], -1),
            np.stack([t * x * z - s * y, t * y * z + s * x, t * z * z + c], -1),
        ],
        -2,
    )


def _about(axis: int, angle: np.ndarray) -> np.ndarray:
    e = np.zeros(np.shape(angle) + (3,))
    e[..., axis] = 1.0
    return _axis_angle(e, np.asarray(angle, dtype=np.float64))


def _swing(frm, to, fallback):
    c = np.clip(np.sum(frm * to, -1), -1.0, 1.0)
    cr = np.cross(frm, to)
    a, ok = _unit(cr, 1e-12)
    r = _axis_angle(a, np.arctan2(np.linalg.norm(cr, axis=-1), c))
    same = ~ok & (c > 0)
    r[same] = np.eye(3)
    opposite = ~ok & ~(c > 0)
    if opposite.any():
        f, fok = _unit(_perp(fallback, frm), 1e-12)
        g, gok = _unit(_perp(np.broadcast_to([1.0, 0.0, 0.0], frm.shape), frm), 1e-6)
        axis = np.where(fok[..., None], f, np.where(gok[..., None], g, [0.0, 1.0, 0.0]))
        r[opposite] = _axis_angle(axis[opposite], np.full(int(opposite.sum()), np.pi))
    return r


def _aim(base, rest_dir, d):
    frm = base @ np.asarray(rest_dir)
    fallback = base @ np.array([0.0, 0.0, 1.0])
    return _swing(frm, d, fallback) @ base


def _hold(theta: np.ndarray, weight: np.ndarray, period: float) -> np.ndarray:
    """The twist each frame applies: ``held += weight * (theta - held)`` (difference taken
    modulo ``period``), so a plane seen clearly sets it and a straight limb keeps the last
    one. It starts where a backward pass over the sequence ends (its first clear plane)."""

    def run(order, held):
        out = np.zeros(len(theta))
        for t in order:
            delta = theta[t] - held
            held += weight[t] * (delta - period * np.round(delta / period))
            out[t] = held
        return out

    start = run(range(len(theta) - 1, -1, -1), 0.0)[0] if len(theta) else 0.0
    return run(range(len(theta)), start)


def _solve(P: np.ndarray) -> np.ndarray:
    """World rotations ``(T, 21, 3, 3)`` of the rig for positions ``P`` (Y-up frame, metres)."""
    T = len(P)
    W = np.zeros((T, len(RIG), 3, 3))
    hips, shoulders = P[:, 4] - P[:, 1], P[:, 11] - P[:, 14]
    for r, (_, parent, at, aim, rest_dir, _, kind, extra) in enumerate(RIG):
        base = W[:, parent] if parent is not None else None
        if kind == "leaf":
            W[:, r] = base
            continue
        d, dok = _unit(P[:, aim] - P[:, at], 1e-9)
        if kind == "frame":
            if extra == "hips":
                x_ref, lok = hips, np.ones(T, bool)
            elif extra == "shoulders":
                x_ref, lok = shoulders, np.ones(T, bool)
            else:
                (h, hok), (s, sok) = _unit(hips, 1e-12), _unit(shoulders, 1e-12)
                x_ref, lok = h + s, hok & sok
            x, xok = _unit(_perp(x_ref, d), 1e-6 * np.maximum(np.linalg.norm(x_ref, axis=-1), 1e-12))
            rest = np.array([rest_dir, _PX, np.cross(rest_dir, _PX)]).T
            got = np.stack([d, x, np.cross(d, x)], -1) @ rest.T
            ok = dok & lok & xok
            if base is None:  # the root: fall back on the previous frame's rotation
                W[ok, r] = got[ok]
                prev = np.eye(3)
                for t in range(T):
                    if not ok[t]:
                        W[t, r] = _aim(prev[None], rest_dir, d[t][None])[0] if dok[t] else prev
                    prev = W[t, r]
            else:
                fb = _aim(base, rest_dir, d)
                W[:, r] = np.where(ok[:, None, None], got, np.where(dok[:, None, None], fb, base))
            continue
        s = _aim(base @ _NEUTRAL[r] if r in _NEUTRAL else base, rest_dir, d)
        if kind == "bend":
            far, rest_bend, fold = extra
            v = P[:, far] - P[:, aim]
            vp = _perp(v, d)
            bend = np.degrees(np.arctan2(np.linalg.norm(vp, axis=-1), np.sum(v * d, -1)))
            x = np.clip((bend - BEND_RAMP_DEG[0]) / (BEND_RAMP_DEG[1] - BEND_RAMP_DEG[0]), 0.0, 1.0)
            weight = x * x * (3.0 - 2.0 * x)
            f, fok = _unit(vp, 1e-12)
            r0 = s @ np.asarray(rest_bend)
            theta = np.arctan2(np.sum(d * np.cross(r0, f), -1), np.sum(r0 * f, -1))
            held = _hold(theta, np.where(fok, weight, 0.0), np.pi if fold else 2.0 * np.pi)
            s = _axis_angle(d, held) @ s
        W[:, r] = np.where(dok[:, None, None], s, base)
    return W


def _locals(W: np.ndarray) -> np.ndarray:
    L = W.copy()
    for r, (_, parent, *_rest) in enumerate(RIG):
        if parent is not None:
            L[:, r] = np.swapaxes(W[:, parent], -1, -2) @ W[:, r]
    return L


def _from_euler(order, angles: np.ndarray) -> np.ndarray:
    return _about(order[0], angles[..., 0]) @ _about(order[1], angles[..., 1]) @ _about(order[2], angles[..., 2])


def _euler(L: np.ndarray) -> np.ndarray:
    """Euler angles ``(T, 21, 3)`` (radians) in each joint's order, nearest the previous frame's."""
    T, n = L.shape[:2]
    cands = np.zeros((T, n, 2, 3))
    gimbal = np.zeros((T, n), bool)
    for r, rig in enumerate(RIG):
        i, j, k = order = rig[5]
        s = 1.0 if order in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1.0
        m = L[:, r]
        sb = np.clip(s * m[:, i, k], -1.0, 1.0)
        b = np.arcsin(sb)
        c = np.arctan2(-s * m[:, i, j], m[:, i, i])
        gimbal[:, r] = np.abs(sb) >= 1.0 - 1e-12
        nn = m @ _about(k, -c) @ _about(j, -b)
        p, q = (i + 1) % 3, (i + 2) % 3
        a = np.arctan2(nn[:, q, p], nn[:, p, p])
        cands[:, r, 0] = np.stack([a, b, c], -1)
        cands[:, r, 1] = np.stack([a + np.pi, np.pi - b, c + np.pi], -1)
    out = np.zeros((T, n, 3))
    prev = np.zeros((n, 3))
    tau = 2.0 * np.pi
    rows = np.arange(n)
    for t in range(T):
        if gimbal[t].any():  # the last angle keeps its previous value
            for r in np.flatnonzero(gimbal[t]):
                i, j, k = RIG[r][5]
                c = prev[r, 2]
                b = cands[t, r, 0, 1]
                nn = L[t, r] @ _about(k, -c) @ _about(j, -b)
                p, q = (i + 1) % 3, (i + 2) % 3
                a = np.arctan2(nn[q, p], nn[p, p])
                cands[t, r, 0] = (a, b, c)
                cands[t, r, 1] = (a + np.pi, np.pi - b, c + np.pi)
        w = cands[t] - tau * np.round((cands[t] - prev[:, None]) / tau)
        cost = np.abs(w - prev[:, None]).sum(-1)
        out[t] = w[rows, np.argmin(cost, axis=1)]
        prev = out[t]
    return out


def _step_angles(L: np.ndarray) -> np.ndarray:
    """``(T-1, 21)`` angle (degrees) between each joint's rotations in consecutive frames."""
    m = np.swapaxes(L[:-1], -1, -2) @ L[1:]
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    skew = np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)
    return np.degrees(np.arctan2(np.linalg.norm(skew, axis=-1) / 2.0, (tr - 1.0) / 2.0))


# ---------------------------------------------------------------- BVH


def _rest_positions(lengths: np.ndarray) -> np.ndarray:
    dirs = {aim: np.asarray(rest) for _, _, _, aim, rest, *_ in RIG if aim is not None}
    pos = np.zeros((17, 3))
    for b in range(16):
        pos[b + 1] = pos[PARENTS[b + 1]] + dirs[b + 1] * lengths[b]
    return pos


def _offsets(lengths: np.ndarray) -> np.ndarray:
    rest = _rest_positions(lengths)
    return np.array([np.zeros(3) if parent is None else rest[at] - rest[RIG[parent][2]]
                     for _, parent, at, *_ in RIG])  # fmt: skip


def _hierarchy(lengths: np.ndarray, frames: int, fps: float) -> str:
    offs = _offsets(lengths)
    lines = ["HIERARCHY"]
    stack: list = []
    for r, (name, parent, at, _, _, order, kind, extra) in enumerate(RIG):
        while stack and stack[-1] != parent:
            stack.pop()
            lines.append("\t" * len(stack) + "}")
        tab = "\t" * len(stack)
        o = offs[r]
        rot = " ".join("XYZ"[a] + "rotation" for a in order)
        chans = f"CHANNELS 6 Xposition Yposition Zposition {rot}" if parent is None else f"CHANNELS 3 {rot}"
        lines += [f"{tab}{'ROOT' if parent is None else 'JOINT'} {name}", tab + "{",
                  f"{tab}\tOFFSET {o[0]:.6f} {o[1]:.6f} {o[2]:.6f}", f"{tab}\t{chans}"]  # fmt: skip
        if kind == "leaf":
            e = np.asarray(extra) * END_SITE_FRACTION * lengths[at - 1]
            lines += [f"{tab}\tEnd Site", f"{tab}\t{{", f"{tab}\t\tOFFSET {e[0]:.6f} {e[1]:.6f} {e[2]:.6f}", f"{tab}\t}}"]
        stack.append(r)
    while stack:
        stack.pop()
        lines.append("\t" * len(stack) + "}")
    lines += ["MOTION", f"Frames: {frames}", f"Frame Time: {1.0 / fps:.9f}"]
    return "\n".join(lines) + "\n"


def _fk(local: np.ndarray, offs: np.ndarray, root: np.ndarray) -> np.ndarray:
    T = len(local)
    world = np.zeros_like(local)
    pos = np.zeros((T, len(RIG), 3))
    for r, (_, parent, *_rest) in enumerate(RIG):
        if parent is None:
            world[:, r], pos[:, r] = local[:, r], root
        else:
            world[:, r] = world[:, parent] @ local[:, r]
            pos[:, r] = pos[:, parent] + world[:, parent] @ offs[r]
    return pos


def bvh_text(poses, lengths=None, *, fps: float = 50.0, up: Optional[Sequence[float]] = None) -> Tuple[str, BvhReport]:
    """The BVH file's text and its :class:`BvhReport` (see :func:`write_bvh`)."""
    fps = _check_fps(fps)
    reposed, lengths = repose(poses, lengths)
    y_up, _ = export_axes(up)
    P = reposed.astype(np.float64) @ y_up.T
    L = _locals(_solve(P))
    deg = np.round(np.degrees(_euler(L)), 6)
    root = np.round(P[:, 0], 6)
    # + 0.0 turns the -0.0 that rounding leaves into 0.0, printed "0.000000" as Rust's writer
    # prints it (never "-0.000000")
    values = np.concatenate([root, deg.reshape(len(P), -1)], axis=1) + 0.0
    body = "\n".join(" ".join(f"{v:.6f}" for v in row) for row in values)
    steps = _step_angles(L) if len(L) > 1 else np.zeros((0, len(RIG)))
    if steps.size:
        t, r = np.unravel_index(int(np.argmax(steps)), steps.shape)
        step, joint, frame = float(steps[t, r]), RIG[r][0], int(t) + 1
    else:
        step, joint, frame = 0.0, RIG[0][0], 0
    written = np.stack([_from_euler(rig[5], np.radians(deg[:, r])) for r, rig in enumerate(RIG)], 1)
    pos = _fk(written, _offsets(lengths), root)
    at = [rig[2] for rig in RIG]
    fk_error = float(np.max(np.linalg.norm(pos - P[:, at], axis=-1)))
    report = BvhReport(len(P), step, joint, frame, fk_error)
    return _hierarchy(lengths, len(P), fps) + body + "\n", report


def write_bvh(path: PathLike, poses, lengths=None, *, fps: float = 50.0,
              up: Optional[Sequence[float]] = None) -> BvhReport:  # fmt: skip
    """Write ``poses`` ``(T, 17, 3)`` (metres) as a BVH; see the module docstring.

    Raises ValueError for no poses, a non-finite pose, a zero-length bone or bad lengths,
    fps or up (nothing is written then), OSError when the file cannot be written."""
    text, report = bvh_text(poses, lengths, fps=fps, up=up)
    Path(path).write_text(text)
    return report


# ---------------------------------------------------------------- markers: C3D and TRC


def _markers_mm(poses, lengths, up) -> np.ndarray:
    reposed, _ = repose(poses, lengths)
    _, z_up = export_axes(up)
    return (reposed.astype(np.float64) * 1000.0) @ z_up.T


def _param(group_id: int, name: str, desc: str, kind: str, value, dims=()) -> bytes:
    head = bytes([len(name), group_id]) + name.encode()
    if kind == "i16":
        body = bytes([2, len(dims)]) + bytes(dims) + np.asarray(value, "<i2").tobytes()
    elif kind == "f32":
        body = bytes([4, len(dims)]) + bytes(dims) + np.asarray(value, "<f4").tobytes()
    else:
        n = max(max(len(s) for s in value), 1)
        shape = [n] if len(value) == 1 else [n, len(value)]
        body = bytes([0xFF, len(shape)]) + bytes(shape) + "".join(s.ljust(n) for s in value).encode()
    return head + b"\0\0" + body + bytes([len(desc)]) + desc.encode()


def _c3d_parameters(frames: int, fps: float, data_start: int) -> bytes:
    names = list(JOINT_NAMES)
    groups = [
        ("POINT", "3D joint centres", [
            ("USED", "number of points", "i16", [17], ()),
            ("SCALE", "negative: float data", "f32", [-1.0], ()),
            ("RATE", "frames per second", "f32", [fps], ()),
            ("DATA_START", "first block of the data", "i16", [data_start], ()),
            ("FRAMES", "number of frames", "i16", [np.uint16(frames).astype(np.int16)], ()),
            ("LABELS", "joint names", "chars", names, ()),
            ("DESCRIPTIONS", "Human3.6M joint centres", "chars", ["blapose joint centre"] * 17, ()),
            ("UNITS", "length unit", "chars", ["mm"], ()),
            ("X_SCREEN", "screen right", "chars", ["+X"], ()),
            ("Y_SCREEN", "screen up: Z is up", "chars", ["+Z"], ()),
        ]),
        ("ANALOG", "no analog channels", [
            ("USED", "number of channels", "i16", [0], ()),
            ("RATE", "samples per second", "f32", [0.0], ()),
        ]),
        ("TRIAL", "frame range", [
            ("ACTUAL_START_FIELD", "first frame, 32-bit", "i16", [1, 0], (2,)),
            ("ACTUAL_END_FIELD", "last frame, 32-bit", "i16",
             [np.uint16(frames & 0xFFFF).astype(np.int16), frames >> 16], (2,)),
        ]),
        ("MANUFACTURER", "who wrote the file", [
            ("COMPANY", "", "chars", ["blapose"], ()),
            ("SOFTWARE", "", "chars", ["blapose-export"], ()),
            ("VERSION_LABEL", "", "chars", ["0.1.0"], ()),
        ]),
    ]  # fmt: skip
    records = []
    for g, (gname, gdesc, params) in enumerate(groups, 1):
        records.append(bytes([len(gname), (256 - g) & 0xFF]) + gname.encode() + b"\0\0" + bytes([len(gdesc)]) + gdesc.encode())
        records += [_param(g, *p) for p in params]
    body = bytearray()
    for i, rec in enumerate(records):
        rec = bytearray(rec)
        at = 2 + rec[0]
        rec[at:at + 2] = struct.pack("<h", 0 if i + 1 == len(records) else len(rec) - at)
        body += rec
    blocks = -(-(4 + len(body)) // 512)
    return (bytes([1, 0x50, blocks, 84]) + bytes(body)).ljust(blocks * 512, b"\0")


def c3d_bytes(poses, lengths=None, *, fps: float = 50.0, up: Optional[Sequence[float]] = None) -> bytes:
    """The C3D file's bytes (see :func:`write_c3d`)."""
    fps = _check_fps(fps)
    mm = _markers_mm(poses, lengths, up)
    frames = len(mm)
    if frames > 65535:
        raise ValueError(f"cannot export: C3D holds at most 65535 frames, the sequence has {frames}")
    data_start = 2 + len(_c3d_parameters(frames, fps, 0)) // 512
    header = bytearray(512)
    struct.pack_into("<BBHHHHH", header, 0, 2, 0x50, 17, 0, 1, frames, 0)
    struct.pack_into("<fHHf", header, 12, -1.0, data_start, 0, fps)
    data = np.zeros((frames, 17, 4), "<f4")
    data[:, :, :3] = mm
    raw = data.tobytes()
    raw += b"\0" * (-len(raw) % 512)
    return bytes(header) + _c3d_parameters(frames, fps, data_start) + raw


def write_c3d(path: PathLike, poses, lengths=None, *, fps: float = 50.0,
              up: Optional[Sequence[float]] = None) -> None:  # fmt: skip
    """Write ``poses`` ``(T, 17, 3)`` (metres) as a C3D: 17 points named as the joints,
    millimetres, Z up, float data, Intel byte order. Errors as :func:`write_bvh`."""
    data = c3d_bytes(poses, lengths, fps=fps, up=up)
    Path(path).write_bytes(data)


def trc_text(poses, lengths=None, *, fps: float = 50.0, up: Optional[Sequence[float]] = None, name: str = "") -> str:
    """The TRC file's text (see :func:`write_trc`)."""
    fps = _check_fps(fps)
    mm = _markers_mm(poses, lengths, up) + 0.0  # no "-0.0000", as Rust writes it (see bvh_text)
    frames = len(mm)
    head = [
        f"PathFileType\t4\t(X/Y/Z)\t{name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{fps:.6f}\t{fps:.6f}\t{frames}\t17\tmm\t{fps:.6f}\t1\t{frames}",
        "Frame#\tTime\t" + "\t\t\t".join(JOINT_NAMES),
        "\t\t" + "\t".join(f"X{k}\tY{k}\tZ{k}" for k in range(1, 18)),
        "",
    ]
    rows = [f"{t + 1}\t{t / fps:.6f}\t" + "\t".join(f"{v:.4f}" for v in mm[t].reshape(-1)) for t in range(frames)]
    return "\n".join(head + rows) + "\n"


def write_trc(path: PathLike, poses, lengths=None, *, fps: float = 50.0,
              up: Optional[Sequence[float]] = None) -> None:  # fmt: skip
    """Write ``poses`` ``(T, 17, 3)`` (metres) as OpenSim's TRC: 17 markers named as the
    joints, millimetres, Z up, tab-separated. Errors as :func:`write_bvh`."""
    path = Path(path)
    path.write_text(trc_text(poses, lengths, fps=fps, up=up, name=path.name))
