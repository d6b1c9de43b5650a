"""A self-contained HTML report of an adjustment: ``write_html``.

The page (``report_template.html``, shipped with the package) shows the input and the
adjusted skeletons side by side in 3D (animated, with play/pause, a frame slider and a
shared orbit camera), the 16 bone lengths over time, the left/right asymmetry and, with
ground truth, the per-frame MPJPE and the before/after table (MPJPE, P-MPJPE,
bone-length error). It needs no network: scripts, styles and data are inline.

``blapose-client replay/adjust --html`` fills the very same template (the Rust client
embeds this file), so both write the same page; only the raw data goes into it (poses as
flat arrays in metres rounded to 0.1 mm, the skeleton, the frame rate, a metrics table
and header lines), and the page derives the rest.

>>> import blapose, blapose.report
>>> seq = blapose.load_replay("examples/cmu_02_02_walk.npz")
>>> with blapose.Client("http://127.0.0.1:50051") as client:
...     res = client.adjust_sequence(seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size)
>>> blapose.report.write_replay_html("walk.html", seq, res, title="cmu_02_02_walk.npz")
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from .replay_file import ReplayFile
from .types import BONE_NAMES, JOINT_NAMES, PARENTS, FrameResult, SequenceResult

__all__ = [
    "DATA_PLACEHOLDER",
    "FORMAT",
    "metrics",
    "read_html_data",
    "render_html",
    "report_data",
    "template",
    "write_html",
    "write_replay_html",
]

#: The template's one placeholder, replaced by the report's JSON data.
DATA_PLACEHOLDER = "__BLAPOSE_REPORT_DATA__"
#: The data's ``format`` field (the Rust client writes the same).
FORMAT = "blapose-report/1"
_DATA_START = '<script id="blapose-data" type="application/json">'
_MM = 1000.0


def template() -> str:
    """The HTML template shipped with the package (one :data:`DATA_PLACEHOLDER`)."""
    return resources.files("blapose").joinpath("report_template.html").read_text(encoding="utf-8")


def _poses(name: str, value: Any, frames: Optional[int]) -> np.ndarray:
    a: np.ndarray = np.asarray(value, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (17, 3):
        raise ValueError(f"{name} must have shape (T, 17, 3), got {a.shape}")
    if a.shape[0] == 0:
        raise ValueError(f"{name} has no frames")
    if frames is not None and a.shape[0] != frames:
        raise ValueError(f"{name} has {a.shape[0]} frames but before has {frames}")
    if not np.all(np.isfinite(a)):
        t, j = np.argwhere(~np.isfinite(a))[0][:2]
        raise ValueError(f"{name}: frame {t}, joint {j} is not finite")
    return a


def _flat(poses: np.ndarray) -> List[float]:
    """Flat list in metres, rounded to 0.1 mm (``0.0 + x`` turns -0.0 into 0.0)."""
    return [0.0 + v for v in np.round(poses.reshape(-1), 4).tolist()]


def _bone_lengths(poses: np.ndarray) -> np.ndarray:
    child = np.arange(1, 17)
    parent = np.asarray(PARENTS)[child]
    lengths: np.ndarray = np.linalg.norm(poses[:, child] - poses[:, parent], axis=-1)
    return lengths


def _procrustes(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``pred`` aligned to ``gt`` per frame by the best similarity transform (as
    ``blapose_core::metrics::procrustes_align``: proper rotation, scale, translation)."""
    mu_x, mu_y = gt.mean(axis=1, keepdims=True), pred.mean(axis=1, keepdims=True)
    x0, y0 = gt - mu_x, pred - mu_y
    norm_y2 = (y0**2).sum(axis=(1, 2))
    h = np.einsum("tji,tjk->tik", x0, y0)  # X0^T Y0
    u, s, vt = np.linalg.svd(h)
    v = np.swapaxes(vt, 1, 2)
    r = v @ np.swapaxes(u, 1, 2)
    flip = np.linalg.det(r) < 0
    v[flip, :, -1] *= -1  # numpy sorts singular values: the last is the smallest
    s[flip, -1] *= -1
    r = v @ np.swapaxes(u, 1, 2)
    safe = np.where(norm_y2 > 0, norm_y2, 1.0)
    a = np.where(norm_y2 > 0, s.sum(axis=1) / safe, 0.0)
    aligned: np.ndarray = a[:, None, None] * (y0 @ r) + mu_x
    return aligned


def metrics(pred: Any, gt: Any) -> Dict[str, float]:
    """MPJPE (root-relative), P-MPJPE and mean absolute bone-length error of ``pred``
    against ``gt`` (both ``(T, 17, 3)`` metres), in millimetres: the client's
    ``PoseMetrics`` (``blapose_core::metrics::pose_metrics``)."""
    p = _poses("pred", pred, None)
    g = _poses("gt", gt, p.shape[0])
    pr, gr = p - p[:, :1], g - g[:, :1]
    return {
        "mpjpe_mm": float(np.linalg.norm(pr - gr, axis=-1).mean() * _MM),
        "p_mpjpe_mm": float(np.linalg.norm(_procrustes(pr, gr) - gr, axis=-1).mean() * _MM),
        "bone_error_mm": float(np.abs(_bone_lengths(p) - _bone_lengths(g)).mean() * _MM),
    }


def report_data(
    before: Any,
    after: Any,
    *,
    gt: Any = None,
    fps: Optional[float] = 50.0,
    title: Optional[str] = None,
    before_label: str = "input",
    after_label: str = "adjusted",
    info: Union[Mapping[str, Any], Iterable[Tuple[str, Any]], None] = None,
    up: Optional[Sequence[float]] = None,
    compute_metrics: bool = True,
    root: Any = None,
) -> Dict[str, Any]:
    """The JSON object a report page reads (see :func:`write_html` for the arguments)."""
    b = _poses("before", before, None)
    r = None
    if root is not None:
        r = np.asarray(root, dtype=np.float64)
        if r.shape != (b.shape[0], 3) or not np.all(np.isfinite(r)):
            raise ValueError(f"root must be ({b.shape[0]}, 3) finite values, got shape {r.shape}")
    a = _poses("after", after, b.shape[0])
    g = None if gt is None else _poses("gt", gt, b.shape[0])
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    if up is not None:
        u = np.asarray(up, dtype=np.float64)
        if u.shape != (3,) or not np.all(np.isfinite(u)) or not np.any(u):
            raise ValueError(f"up must be 3 finite values, not all zero, got {up!r}")
    items = list(info.items()) if isinstance(info, Mapping) else list(info or [])
    table = None
    if g is not None and compute_metrics:
        table = {"frames": int(b.shape[0]), "before": metrics(b, g), "after": metrics(a, g)}
    return {
        "format": FORMAT,
        "title": title,
        "frames": int(b.shape[0]),
        "fps": None if fps is None else float(fps),
        "skeleton": {"joint_names": list(JOINT_NAMES), "bone_names": list(BONE_NAMES), "parents": list(PARENTS)},
        "up": None if up is None else [float(v) for v in up],
        "before_label": before_label,
        "after_label": after_label,
        "before": _flat(b),
        "after": _flat(a),
        "gt": None if g is None else _flat(g),
        "metrics": table,
        "info": [[str(k), str(v)] for k, v in items],
        "root": None if r is None else _flat(r),
    }


def _embed(data: Mapping[str, Any]) -> str:
    # Every "<" escaped: no string in the data can close the script tag ("</script>")
    # or open a comment ("<!--"); JSON.parse reads \u003c back as "<".
    text = json.dumps(data, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    return text.replace("<", "\\u003c")


def render_html(before: Any, after: Any, **kwargs: Any) -> str:
    """The report page as a string; arguments as :func:`write_html`."""
    page = template()
    if page.count(DATA_PLACEHOLDER) != 1:
        raise RuntimeError("the report template must hold exactly one data placeholder")
    return page.replace(DATA_PLACEHOLDER, _embed(report_data(before, after, **kwargs)))


def write_html(
    path: Union[str, Path],
    before: Any,
    after: Any,
    *,
    gt: Any = None,
    fps: Optional[float] = 50.0,
    title: Optional[str] = None,
    before_label: str = "input",
    after_label: str = "adjusted",
    info: Union[Mapping[str, Any], Iterable[Tuple[str, Any]], None] = None,
    up: Optional[Sequence[float]] = None,
    compute_metrics: bool = True,
    root: Any = None,
) -> Path:
    """Write a self-contained HTML report comparing ``before`` and ``after`` poses.

    Args:
        path: the ``.html`` file to write.
        before: ``(T, 17, 3)`` the poses the adjustment started from (metres,
            Human3.6M joint order, any Cartesian frame).
        after: ``(T, 17, 3)`` the adjusted poses.
        gt: optional ``(T, 17, 3)`` ground truth in the same frame: adds the per-frame
            MPJPE plot and the before/after table.
        fps: frame rate for playback and time axes (None: unknown, plays at 25).
        title: shown in the header (e.g. the replay file's name).
        before_label, after_label: names of the two pose sets.
        info: extra header lines, ``{"model": "bigru", ...}`` or ``(key, value)`` pairs.
        up: world "up" in the poses' coordinates (default ``(0, -1, 0)``: a camera
            frame with y down, as lifters and the replay files use).
        compute_metrics: with ``gt``, compute the table (MPJPE, P-MPJPE, bone-length
            error) here as the client does; False leaves it to the page (no P-MPJPE).
        root: optional ``(T, 3)`` pelvis positions in the poses' axes (a motion
            answer's ``root_positions``): adds the pelvis path seen from above, so the
            page shows the person moving through space.

    Returns:
        The path written.

    Raises:
        ValueError: wrong shapes, frame counts that differ, non-finite values, a bad
            ``fps`` or ``up``.
    """
    html = render_html(
        before,
        after,
        gt=gt,
        fps=fps,
        title=title,
        before_label=before_label,
        after_label=after_label,
        info=info,
        up=up,
        compute_metrics=compute_metrics,
        root=root,
    )
    out = Path(path)
    out.write_text(html, encoding="utf-8")
    return out


def _adjusted_poses(adjusted: Union[np.ndarray, SequenceResult, Iterable[FrameResult], Any]) -> np.ndarray:
    if isinstance(adjusted, SequenceResult):
        return np.asarray(adjusted.adjusted)
    if isinstance(adjusted, np.ndarray):
        return adjusted
    items = list(adjusted)
    if items and isinstance(items[0], FrameResult):
        return np.stack([r.adjusted for r in items])
    return np.asarray(items)


def _roots(adjusted: Any) -> Optional[np.ndarray]:
    """The pelvis positions a motion answer carries, ``(T, 3)``; None without."""
    if isinstance(adjusted, SequenceResult):
        return adjusted.root_positions
    if isinstance(adjusted, list) and adjusted and all(isinstance(r, FrameResult) and r.root is not None for r in adjusted):
        return np.stack([r.root for r in adjusted])
    return None


def write_replay_html(
    path: Union[str, Path],
    replay: ReplayFile,
    adjusted: Union[np.ndarray, SequenceResult, Iterable[FrameResult]],
    **kwargs: Any,
) -> Path:
    """:func:`write_html` for a replay file and what the server answered for it:
    ``adjusted`` is a :class:`SequenceResult` (``adjust_sequence``), the
    :class:`FrameResult` list of a session's ``stream``, or a ``(T, 17, 3)`` array.
    ``before`` is the file's ``pose_3d``, ``gt`` its ``gt_3d``, ``fps`` its ``fps``
    (else 50), ``up`` its camera's up direction, ``root`` the answers' pelvis
    positions when they carry them (``motion``); ``kwargs`` go to :func:`write_html`."""
    if not isinstance(adjusted, (np.ndarray, SequenceResult)):
        adjusted = list(adjusted)
    roots = _roots(adjusted)
    if roots is not None:
        kwargs.setdefault("root", roots)
    kwargs.setdefault("gt", replay.gt_3d)
    kwargs.setdefault("fps", replay.fps if replay.fps else 50.0)
    if replay.camera is not None:
        kwargs.setdefault("up", replay.camera.up)
    if isinstance(adjusted, SequenceResult) and adjusted.model:
        info = dict(kwargs.pop("info", None) or {})
        info.setdefault("model", adjusted.model)
        kwargs["info"] = info
    return write_html(path, replay.pose_3d, _adjusted_poses(adjusted), **kwargs)


def read_html_data(path_or_html: Union[str, Path]) -> Dict[str, Any]:
    """The JSON data embedded in a report (written by Python or by ``blapose-client``)."""
    text = str(path_or_html)
    if not text.lstrip().startswith("<"):
        text = Path(path_or_html).read_text(encoding="utf-8")
    start = text.index(_DATA_START) + len(_DATA_START)
    end = text.index("</script>", start)
    data: Dict[str, Any] = json.loads(text[start:end])
    return data
