"""blapose: Python client for the blapose bone-length adjustment server.

>>> import blapose
>>> with blapose.Client("http://127.0.0.1:50051") as client:
...     with client.session(layout="coco17", image_size=(1920, 1080)) as s:
...         result = s.send(keypoints, pose)   # (17, 2) pixels, (17, 3) metres
...         result.adjusted, result.bone_lengths  # (17, 3), (16,)

See :class:`Client`, :class:`Session`, :mod:`blapose.errors`, :mod:`blapose.aio` and
:mod:`blapose.report` (``write_html``: a self-contained HTML report of an adjustment) and
:mod:`blapose.export` (``write_bvh``, ``write_c3d``, ``write_trc``: the motion for animation and
biomechanics tools).
"""

from . import aio, export, report
from ._common import MISSING_CONFIDENCE
from .client import Client, Session
from .errors import (
    Aborted,
    BlaposeError,
    Cancelled,
    DeadlineExceeded,
    FailedPrecondition,
    FrameRejected,
    Internal,
    InvalidArgument,
    NotFound,
    OutOfRange,
    PermissionDenied,
    ProtocolError,
    ResourceExhausted,
    RpcError,
    Unauthenticated,
    Unavailable,
    Unimplemented,
    UnknownError,
)
from .export import write_bvh, write_c3d, write_trc
from .report import write_html, write_replay_html
from .types import (
    BONE_NAMES,
    JOINT_NAMES,
    LAYOUTS,
    PARENTS,
    Camera,
    ClosedSession,
    FrameResult,
    ModelInfo,
    SequenceResult,
    SessionInfo,
    SessionToken,
    adjust_pose,
)
from .replay_file import DEFAULT_MAX_FRAMES, ReplayFile, ReplayFileError, load_replay

__version__ = "0.1.0"

__all__ = [
    "MISSING_CONFIDENCE",
    "aio",
    "report",
    "export",
    "write_bvh",
    "write_c3d",
    "write_trc",
    "write_html",
    "write_replay_html",
    "Client",
    "Session",
    "Camera",
    "ClosedSession",
    "FrameResult",
    "ModelInfo",
    "ReplayFile",
    "ReplayFileError",
    "DEFAULT_MAX_FRAMES",
    "SequenceResult",
    "SessionInfo",
    "SessionToken",
    "adjust_pose",
    "load_replay",
    "JOINT_NAMES",
    "BONE_NAMES",
    "PARENTS",
    "LAYOUTS",
    "BlaposeError",
    "RpcError",
    "FrameRejected",
    "ProtocolError",
    "Aborted",
    "Cancelled",
    "DeadlineExceeded",
    "FailedPrecondition",
    "Internal",
    "InvalidArgument",
    "NotFound",
    "OutOfRange",
    "PermissionDenied",
    "ResourceExhausted",
    "Unauthenticated",
    "Unavailable",
    "Unimplemented",
    "UnknownError",
]
