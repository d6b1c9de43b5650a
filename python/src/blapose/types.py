"""Plain-Python/numpy types: layouts, camera calibration, results, replay files.

Array conventions (the proto's, as numpy arrays):

* 3D poses: ``(17, 3)`` float, metres, Human3.6M joint order (see ``JOINT_NAMES``).
* 2D keypoints: ``(J, 2)`` float, the session layout's joint order
  (J = 17 for ``coco17`` and ``h36m17``, 16 for ``sh16``), pixels of an image of
  ``image_size = (width, height)``, or normalized when ``image_size`` is None.
* Bone lengths: ``(16,)`` float, metres, bone order (see ``BONE_NAMES``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Tuple, Union
from typing import Sequence as Seq

import numpy as np

from .v1 import blapose_pb2 as pb

__all__ = [
    "JOINT_NAMES",
    "BONE_NAMES",
    "PARENTS",
    "LAYOUTS",
    "Camera",
    "SessionInfo",
    "FrameResult",
    "SequenceResult",
    "ClosedSession",
    "SessionToken",
    "ModelInfo",
    "adjust_pose",
]

JOINT_NAMES: Tuple[str, ...] = (
    "pelvis",
    "r_hip",
    "r_knee",
    "r_ankle",
    "l_hip",
    "l_knee",
    "l_ankle",
    "spine",
    "thorax",
    "neck_nose",
    "head",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
    "r_shoulder",
    "r_elbow",
    "r_wrist",
)
BONE_NAMES: Tuple[str, ...] = (
    "r_hip",
    "r_thigh",
    "r_calf",
    "l_hip",
    "l_thigh",
    "l_calf",
    "spine",
    "thorax",
    "neck",
    "head",
    "l_shoulder",
    "l_upper_arm",
    "l_forearm",
    "r_shoulder",
    "r_upper_arm",
    "r_forearm",
)
#: Parent of each Human3.6M joint (joint 0 is the root); bone i joins joint i+1 to PARENTS[i+1].
PARENTS: Tuple[int, ...] = (0, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15)

#: Layout name -> (proto enum value, number of joints).
LAYOUTS: Dict[str, Tuple[int, int]] = {
    "h36m17": (pb.KEYPOINT_LAYOUT_H36M_17, 17),
    "sh16": (pb.KEYPOINT_LAYOUT_SH_16, 16),
    "coco17": (pb.KEYPOINT_LAYOUT_COCO_17, 17),
}
_LAYOUT_BY_VALUE = {v[0]: k for k, v in LAYOUTS.items()}
_MODELS = {
    None: pb.MODEL_UNSPECIFIED,
    "gru": pb.MODEL_ONLINE_GRU,
    "bigru": pb.MODEL_OFFLINE_BIGRU,
}
_MODEL_NAMES = {pb.MODEL_UNSPECIFIED: None, pb.MODEL_ONLINE_GRU: "gru", pb.MODEL_OFFLINE_BIGRU: "bigru"}

Layout = Union[str, int]
ArrayLike = Any


def layout_value(layout: Layout) -> Tuple[int, int]:
    """(proto enum value, joint count) for a layout name or proto number."""
    if isinstance(layout, str):
        key = layout.lower().replace("-", "").replace("_", "")
        if key not in LAYOUTS:
            raise ValueError(f"unknown layout {layout!r}; expected one of {sorted(LAYOUTS)}")
        return LAYOUTS[key]
    value = int(layout)
    if value not in _LAYOUT_BY_VALUE:
        # Let the server judge numbers it may know; joint count unknown.
        return value, -1
    return value, LAYOUTS[_LAYOUT_BY_VALUE[value]][1]


def model_value(model: Optional[Union[str, int]]) -> int:
    """Proto ``Model`` value for ``None``/``"gru"``/``"bigru"`` (or a number)."""
    if model is None or isinstance(model, str):
        if model not in _MODELS:
            raise ValueError(f"unknown model {model!r}; expected 'gru', 'bigru' or None")
        return _MODELS[model]
    return int(model)


def model_name(value: int) -> Optional[str]:
    return _MODEL_NAMES.get(value, str(value))  # type: ignore[call-overload]


def input_format(layout: Layout, image_size: Optional[Tuple[int, int]]) -> pb.InputFormat:
    """The proto ``InputFormat``: pixels of ``image_size=(w, h)``, or normalized if None."""
    fmt = pb.InputFormat(layout=layout_value(layout)[0])  # type: ignore[arg-type]
    if image_size is None:
        fmt.normalized = True
    else:
        w, h = image_size
        fmt.image_size.width = int(w)
        fmt.image_size.height = int(h)
    return fmt


@dataclass(frozen=True)
class Camera:
    """A camera calibration (proto ``CameraCalibration``); serves the camera-aware models.

    Attributes:
        up: world "up" in camera coordinates (x right, y down, z forward), 3 values.
        focal: ``(fx, fy)`` in pixels.
        principal: ``(cx, cy)`` in pixels.
        image_size: ``(w, h)`` the values refer to; needed with normalized keypoints.
        height: camera height above the floor in metres (0.3-10), or None. The shipped
            camera-aware models require it: they were trained for cameras 0.5-3 m high,
            -35 to +15 degrees from level, 40-100 degrees across, and the server refuses
            other calibrations with ``InvalidArgument`` naming the value.
        distortion: the lens's distortion in OpenCV's order, ``(k1, k2, p1, p2)`` or
            ``(k1, k2, p1, p2, k3)`` (what ``cv2.calibrateCamera`` reports), for keypoints
            detected in the raw image; the server undoes it first. None: the keypoints
            are undistorted pixels.
    """

    up: Tuple[float, float, float]
    focal: Tuple[float, float]
    principal: Tuple[float, float]
    image_size: Optional[Tuple[int, int]] = None
    height: Optional[float] = None
    distortion: Optional[Tuple[float, ...]] = None

    def to_proto(self) -> pb.CameraCalibration:
        cam = pb.CameraCalibration(
            up=[float(v) for v in self.up],
            focal_x=float(self.focal[0]),
            focal_y=float(self.focal[1]),
            principal_x=float(self.principal[0]),
            principal_y=float(self.principal[1]),
            height=float(self.height or 0.0),
            distortion=[float(v) for v in self.distortion or ()],
        )
        if self.image_size is not None:
            cam.image_size.width = int(self.image_size[0])
            cam.image_size.height = int(self.image_size[1])
        return cam

    @staticmethod
    def from_proto(cam: pb.CameraCalibration) -> "Camera":
        return Camera(
            up=tuple(cam.up),  # type: ignore[arg-type]
            focal=(cam.focal_x, cam.focal_y),
            principal=(cam.principal_x, cam.principal_y),
            image_size=(cam.image_size.width, cam.image_size.height) if cam.HasField("image_size") else None,
            height=cam.height or None,
            distortion=tuple(cam.distortion) or None,
        )


def _lengths(values: Seq[float]) -> Optional[np.ndarray]:
    return np.asarray(values, dtype=np.float32) if len(values) else None


@dataclass(frozen=True)
class SessionInfo:
    """A session as the server described it when the stream attached (``SessionOpened``)."""

    session_id: str
    resumed: bool
    frames_seen: int
    bone_lengths: Optional[np.ndarray]
    model: Optional[str]
    session_ttl_ms: int
    lifter: Optional[str]
    camera: Optional[Camera]
    layout: Optional[str] = None
    image_size: Optional[Tuple[int, int]] = None

    @staticmethod
    def from_proto(msg: pb.SessionOpened) -> "SessionInfo":
        fmt = msg.input_format
        return SessionInfo(
            layout=_LAYOUT_BY_VALUE.get(fmt.layout),
            image_size=(fmt.image_size.width, fmt.image_size.height)
            if fmt.WhichOneof("coordinates") == "image_size"
            else None,
            session_id=msg.session_id,
            resumed=msg.resumed,
            frames_seen=msg.frames_seen,
            bone_lengths=_lengths(msg.bone_lengths),
            model=model_name(msg.model),
            session_ttl_ms=msg.session_ttl_ms,
            lifter=msg.lifter or None,
            camera=Camera.from_proto(msg.camera) if msg.HasField("camera") else None,
        )


@dataclass(frozen=True)
class FrameResult:
    """The answer to one frame.

    Attributes:
        frame_index: the index the frame was sent with.
        adjusted: ``(17, 3)`` adjusted pose, metres.
        bone_lengths: ``(16,)`` the session's estimate after this frame, metres.
        frames_seen: frames the session has processed, this one included.
        lifted: ``(17, 3)`` the server lifter's pose before adjustment (server-lifter
            sessions), else None.
        lifter: the server lifter's name, else None.
        recovered: True when the server processed this frame but its answer was
            lost with a dropped connection; the library rebuilt it locally from the
            resumed session's estimate (see :meth:`blapose.Session.stream`); such a
            frame has no motion fields.
        root: with ``motion``, ``(3,)`` the pelvis in camera space (metres; x right,
            y down, z forward), else None. ``adjusted + root`` is the placed pose.
        world: with ``motion`` and a camera with a height, ``(17, 3)`` the placed pose
            in world coordinates (floor at 0), else None.
        focal_assumed: with ``motion`` and no camera: the root was placed through an
            assumed focal length (the image's larger side), so it scales with the true one.
    """

    frame_index: int
    adjusted: np.ndarray
    bone_lengths: np.ndarray
    frames_seen: int
    lifted: Optional[np.ndarray] = None
    lifter: Optional[str] = None
    recovered: bool = False
    root: Optional[np.ndarray] = None
    world: Optional[np.ndarray] = None
    focal_assumed: bool = False

    @staticmethod
    def from_proto(msg: pb.AdjustedFrame) -> "FrameResult":
        return FrameResult(
            frame_index=msg.frame_index,
            adjusted=np.asarray(msg.adjusted_pose_3d, dtype=np.float32).reshape(17, 3),
            bone_lengths=np.asarray(msg.bone_lengths, dtype=np.float32),
            frames_seen=msg.frames_seen,
            lifted=np.asarray(msg.lifted_pose_3d, dtype=np.float32).reshape(17, 3) if len(msg.lifted_pose_3d) else None,
            lifter=msg.lifter or None,
            root=np.asarray(msg.root_position, dtype=np.float32) if len(msg.root_position) == 3 else None,
            world=np.asarray(msg.world_pose_3d, dtype=np.float32).reshape(17, 3) if len(msg.world_pose_3d) else None,
            focal_assumed=msg.focal_assumed,
        )


@dataclass(frozen=True)
class SequenceResult:
    """The answer to :meth:`blapose.Client.adjust_sequence`.

    Attributes:
        adjusted: ``(T, 17, 3)`` adjusted poses.
        bone_lengths: ``(T, 16)`` lengths applied to each frame (all rows equal for the Bi-GRU).
        model: ``"bigru"`` or ``"gru"``.
        root_positions: with ``motion``, ``(T, 3)`` pelvis positions in camera space
            (metres; x right, y down, z forward), else None.
        focal_assumed: the root was placed through an assumed focal length (no camera).
        world_poses: with ``motion`` and a camera with a height, ``(T, 17, 3)`` poses in
            the world (z up, the floor at 0), else None.
    """

    adjusted: np.ndarray
    bone_lengths: np.ndarray
    model: Optional[str]
    root_positions: Optional[np.ndarray] = None
    focal_assumed: bool = False
    world_poses: Optional[np.ndarray] = None


@dataclass(frozen=True)
class ClosedSession:
    """A closed session's final state."""

    session_id: str
    frames_seen: int
    bone_lengths: Optional[np.ndarray]


@dataclass(frozen=True)
class SessionToken:
    """A session token: the session's whole state, as of ``frames_seen`` frames,
    authenticated by the servers' shared ``--session-key``.

    Pass it to :meth:`blapose.Client.resume` to restore the session on any
    replica with the same key (sessions resume with it automatically; see
    :class:`blapose.Session`). Whoever holds it can resume the session: treat
    it as a secret.

    Attributes:
        session_id: the session it belongs to.
        frames_seen: frames processed in the state it holds; a session restored
            from it continues with this frame.
        token: the opaque bytes (about 4.5 kB).
    """

    session_id: str
    frames_seen: int
    token: bytes = field(repr=False)


@dataclass(frozen=True)
class ModelInfo:
    """What the server runs (``ModelInfoResponse``); ``raw`` is the full proto message."""

    server_version: str
    protocol: str
    models: Tuple[Dict[str, Any], ...]
    layouts: Tuple[str, ...]
    joint_names: Tuple[str, ...]
    bone_names: Tuple[str, ...]
    max_sessions: int
    session_ttl_ms: int
    max_batch: int
    max_message_bytes: int
    lifter: Optional[Dict[str, Any]]
    raw: pb.ModelInfoResponse = field(repr=False)

    @staticmethod
    def from_proto(msg: pb.ModelInfoResponse) -> "ModelInfo":
        models = tuple(
            {
                "model": model_name(m.model),
                "name": m.name,
                "parameter_count": m.parameter_count,
                "hidden_size": m.hidden_size,
                "weights_source": m.weights_source,
                "weights_sha256": m.weights_sha256,
                "metadata": dict(m.metadata),
                "camera_aware": m.camera_aware,
            }
            for m in msg.models
        )
        lifter = None
        if msg.HasField("lifter"):
            lf = msg.lifter
            lifter = {
                "name": lf.name,
                "receptive_field": lf.receptive_field,
                "parameter_count": lf.parameter_count,
                "causal": lf.causal,
                "weights_source": lf.weights_source,
                "weights_sha256": lf.weights_sha256,
                "metadata": dict(lf.metadata),
            }
        return ModelInfo(
            server_version=msg.server_version,
            protocol=msg.protocol,
            models=models,
            layouts=tuple(_LAYOUT_BY_VALUE.get(v, str(v)) for v in msg.layouts),
            joint_names=tuple(msg.joint_names),
            bone_names=tuple(msg.bone_names),
            max_sessions=msg.max_sessions,
            session_ttl_ms=msg.session_ttl_ms,
            max_batch=msg.max_batch,
            max_message_bytes=msg.max_message_bytes,
            lifter=lifter,
            raw=msg,
        )


def adjust_pose(pose: ArrayLike, bone_lengths: ArrayLike) -> np.ndarray:
    """Rebuild a ``(17, 3)`` pose with its own bone directions and ``bone_lengths``
    (16), root kept: what the server does to every frame (computed here in float64)."""
    p = np.asarray(pose, dtype=np.float64).reshape(17, 3)
    lengths = np.asarray(bone_lengths, dtype=np.float64).reshape(16)
    out = np.empty_like(p)
    out[0] = p[0]
    for j in range(1, 17):  # parents precede children in Human3.6M order
        parent = PARENTS[j]
        d = p[j] - p[parent]
        out[j] = out[parent] + d / np.linalg.norm(d) * lengths[j - 1]
    return out.astype(np.float32)
