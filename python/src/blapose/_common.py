"""Pieces shared by the sync and asyncio clients (no I/O here)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, List, Optional, Tuple, Union
from typing import Sequence as Seq
from urllib.parse import urlparse

import grpc
import numpy as np

from .errors import FrameRejected, ProtocolError, RpcError, Unavailable, status_code
from .types import (
    Camera,
    FrameResult,
    Layout,
    SequenceResult,
    SessionInfo,
    adjust_pose,
    input_format,
    layout_value,
    model_name,
    model_value,
)
from .v1 import blapose_pb2 as pb

#: Channel options: reconnect quickly after a dropped connection.
CHANNEL_OPTIONS: List[Tuple[str, Any]] = [
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 1000),
    ("grpc.max_receive_message_length", 64 * 1024 * 1024),
    ("grpc.max_send_message_length", 64 * 1024 * 1024),
]


@dataclass(frozen=True)
class Endpoint:
    target: str
    tls: bool


def parse_url(url: str, tls: Optional[bool]) -> Endpoint:
    """``http://host:port`` (plaintext) or ``https://host[:port]`` (TLS) -> target."""
    if "://" not in url:
        return Endpoint(url, bool(tls))
    u = urlparse(url)
    if u.scheme not in ("http", "https", "grpc", "grpcs"):
        raise ValueError(f"unsupported URL scheme {u.scheme!r} in {url!r} (use http:// or https://)")
    secure = u.scheme in ("https", "grpcs") if tls is None else tls
    if not u.hostname:
        raise ValueError(f"no host in {url!r}")
    host = f"[{u.hostname}]" if ":" in u.hostname else u.hostname
    port = u.port or (443 if secure else 50051)
    return Endpoint(f"{host}:{port}", secure)


def credentials(ca_cert: Optional[Union[str, bytes, Path]]) -> grpc.ChannelCredentials:
    root = None
    if ca_cert is not None:
        root = ca_cert if isinstance(ca_cert, bytes) else Path(ca_cert).read_bytes()
    return grpc.ssl_channel_credentials(root_certificates=root)


def metadata(token: Optional[str]) -> Tuple[Tuple[str, str], ...]:
    return (("authorization", f"Bearer {token}"),) if token else ()


def _array(values, shape: Tuple[int, ...], what: str) -> np.ndarray:
    a = np.asarray(values, dtype=np.float32)
    if a.size != int(np.prod(shape)):
        raise ValueError(f"{what} has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has a non-finite value")
    return a.reshape(shape)


@dataclass
class PendingFrame:
    """A frame sent on the stream whose answer has not arrived yet."""

    request: pb.StreamRequest
    frame_index: int
    pose: Optional[np.ndarray]  # (17, 3), None in server-lifter sessions


class SessionCore:
    """The session bookkeeping behind :class:`blapose.Session` and its asyncio twin.

    It numbers frames, keeps the frames in flight in order, matches answers to
    them, and after a resume decides which in-flight frames the server already
    processed (answers rebuilt locally) and which must be sent again.
    """

    def __init__(self, joints: int, server_lifter: bool) -> None:
        self.joints = joints
        self.server_lifter = server_lifter
        self.info: Optional[SessionInfo] = None
        self.frames_seen = 0  # processed frames known to the client
        self.next_index = 0
        self.pending: "list[PendingFrame]" = []
        self.ready: "list[FrameResult]" = []
        self.resumes = 0
        self.recovered = 0

    def attached(self, info: SessionInfo, first: bool) -> None:
        self.info = info
        if first:
            self.frames_seen = info.frames_seen
            self.next_index = max(self.next_index, info.frames_seen)

    def make_frame(
        self,
        keypoints,
        pose=None,
        confidence=None,
        frame_index: Optional[int] = None,
    ) -> PendingFrame:
        j = self.joints if self.joints > 0 else int(np.asarray(keypoints).size // 2)
        kp = _array(keypoints, (j, 2), "keypoints")
        frame = pb.Frame(keypoints_2d=kp.ravel().tolist())
        p = None
        if self.server_lifter:
            if pose is not None:
                raise ValueError("a server-lifter session sends keypoints only (pose must be None)")
        else:
            if pose is None:
                raise ValueError("pose is required (the session was not opened with server_lifter=True)")
            p = _array(pose, (17, 3), "pose")
            frame.pose_3d.extend(p.ravel().tolist())
        if confidence is not None:
            c = np.asarray(confidence, dtype=np.float32)
            if c.size != j:
                raise ValueError(f"confidence has {c.size} values, expected {j}")
            frame.confidence.extend(c.ravel().tolist())
        if frame_index is None:
            frame_index = self.next_index
        frame.frame_index = int(frame_index)
        self.next_index = int(frame_index) + 1
        return PendingFrame(pb.StreamRequest(frame=frame), int(frame_index), p)

    def answer(self, resp: pb.StreamResponse) -> Union[FrameResult, FrameRejected]:
        """Match one stream response to the oldest frame in flight."""
        kind = resp.WhichOneof("kind")
        if not self.pending:
            raise ProtocolError(f"got a {kind!r} response with no frame in flight")
        frame = self.pending.pop(0)
        if kind == "frame":
            msg = resp.frame
            if msg.frame_index != frame.frame_index:
                raise ProtocolError(f"answer for frame {msg.frame_index}, expected {frame.frame_index}")
            if msg.frames_seen != self.frames_seen + 1:
                raise ProtocolError(f"frames_seen {msg.frames_seen}, expected {self.frames_seen + 1}")
            self.frames_seen = msg.frames_seen
            return FrameResult.from_proto(msg)
        if kind == "error":
            msg = resp.error
            return FrameRejected(msg.frame_index, status_code(msg.code), msg.message)
        raise ProtocolError(f"expected a frame answer, got {kind!r}")

    def after_resume(self) -> "list[PendingFrame]":
        """Account for the frames in flight when the connection dropped, once
        ``attached`` has stored the resumed session's ``info``.

        The first ``info.frames_seen - frames_seen`` of them were processed (their
        answers are rebuilt locally and queued in ``ready``); the rest are
        returned, to be sent again in order. Assumes none of the lost answers was
        a refusal (a refused frame is not counted; see the README).
        """
        info = self.info
        assert info is not None
        processed = info.frames_seen - self.frames_seen
        if processed < 0 or processed > len(self.pending):
            raise ProtocolError(
                f"resumed session has frames_seen={info.frames_seen}, but {self.frames_seen} were "
                f"answered and {len(self.pending)} were in flight"
            )
        lengths = info.bone_lengths
        for i in range(processed):
            f = self.pending.pop(0)
            assert lengths is not None
            adjusted = adjust_pose(f.pose, lengths) if f.pose is not None else np.full((17, 3), np.nan, np.float32)
            self.ready.append(
                FrameResult(
                    frame_index=f.frame_index,
                    adjusted=adjusted,
                    bone_lengths=lengths.copy(),
                    frames_seen=self.frames_seen + i + 1,
                    recovered=True,
                )
            )
        self.recovered += processed
        self.frames_seen = info.frames_seen
        self.resumes += 1
        return list(self.pending)


def resumable(err: RpcError) -> bool:
    """A dropped connection (not a server shutting down, whose sessions end with it)."""
    return isinstance(err, Unavailable) and "shutting down" not in err.details


def open_request(
    layout: Layout,
    image_size: Optional[Tuple[int, int]],
    model: Optional[Union[str, int]],
    camera: Optional[Camera],
    server_lifter: bool,
    label: Optional[str],
) -> Tuple[pb.StreamRequest, int]:
    value, joints = layout_value(layout)
    fmt = input_format(value, image_size)
    req = pb.OpenSession(
        input_format=fmt,
        model=model_value(model),  # type: ignore[arg-type]
        client_label=label or "",
        server_lifter=server_lifter,
    )
    if camera is not None:
        req.camera.CopyFrom(camera.to_proto())
    return pb.StreamRequest(open=req), joints


def sequence_request(
    keypoints,
    poses,
    layout: Layout,
    image_size: Optional[Tuple[int, int]],
    model: Optional[Union[str, int]],
    camera: Optional[Camera],
    confidence,
) -> Tuple[pb.AdjustSequenceRequest, int]:
    value, joints = layout_value(layout)
    kp = np.asarray(keypoints, dtype=np.float32)
    t = int(kp.shape[0]) if kp.ndim >= 1 else 0
    if joints < 0:
        joints = int(kp[0].size // 2) if t else 0
    kp = _array(kp, (t, joints, 2), "keypoints")
    ps = _array(poses, (t, 17, 3), "poses")
    req = pb.AdjustSequenceRequest(
        input_format=input_format(value, image_size),
        model=model_value(model),  # type: ignore[arg-type]
        num_frames=t,
        keypoints_2d=kp.ravel().tolist(),
        poses_3d=ps.ravel().tolist(),
    )
    if confidence is not None:
        req.confidence.extend(np.asarray(confidence, dtype=np.float32).ravel().tolist())
    if camera is not None:
        req.camera.CopyFrom(camera.to_proto())
    return req, t


def sequence_result(resp: pb.AdjustSequenceResponse, t: int) -> SequenceResult:
    return SequenceResult(
        adjusted=np.asarray(resp.adjusted_poses_3d, dtype=np.float32).reshape(t, 17, 3),
        bone_lengths=np.asarray(resp.bone_lengths, dtype=np.float32).reshape(t, 16),
        model=model_name(resp.model),
    )


def split_item(item) -> Tuple:
    """A ``stream()`` item: ``(keypoints, pose)``, ``(keypoints, pose, confidence)``,
    or bare keypoints in a server-lifter session."""
    if isinstance(item, tuple):
        if len(item) == 2:
            return item[0], item[1], None
        if len(item) == 3:
            return item
        raise ValueError(f"a frame is (keypoints, pose[, confidence]); got a {len(item)}-tuple")
    return item, None, None


__all__: Seq[str] = []
