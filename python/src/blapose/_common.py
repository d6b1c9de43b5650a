"""Pieces shared by the sync and asyncio clients (no I/O here)."""

from __future__ import annotations

import secrets
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, List, Optional, Tuple, Union
from typing import Sequence as Seq
from urllib.parse import urlparse

import grpc
import numpy as np

from .errors import Cancelled, FrameRejected, ProtocolError, RpcError, Unavailable, UnknownError, status_code
from .types import (
    Camera,
    FrameResult,
    Layout,
    SequenceResult,
    SessionInfo,
    SessionToken,
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


#: The gRPC metadata key a load balancer hashes on to keep a session on one replica.
AFFINITY_HEADER = "blapose-affinity"

#: How many times in a row a session resumes (with no new answer in between) before giving up.
MAX_RESUMES = 8

#: A session holding a token asks for a fresh one (``TokenRequest``) once this many frames were
#: answered since it, so the frames kept to send again stay few (a server's ``--token-every`` may be 0).
TOKEN_REFRESH = 500


def new_affinity() -> str:
    """A random affinity key: 32 lowercase hex characters."""
    return secrets.token_hex(16)


def urls(url: "Union[str, Seq[str]]") -> List[str]:
    """One server URL, or a list of replicas (the first is tried first)."""
    out = [url] if isinstance(url, str) else list(url)
    if not out or not all(isinstance(u, str) and u for u in out):
        raise ValueError(f"expected a server URL or a non-empty list of them, got {url!r}")
    return out


#: Below this detector confidence a joint is missing: the server does not read
#: its keypoint (NaN is fine there) and the models hold it at its last detection.
MISSING_CONFIDENCE = 0.1


def _keypoints(values, confidence, shape: Tuple[int, ...]) -> np.ndarray:
    """Keypoints of ``shape`` (..., J, 2); a missing joint's (confidence below
    :data:`MISSING_CONFIDENCE`) may be anything, NaN included: it is sent as 0."""
    a = np.array(values, dtype=np.float32)
    if confidence is not None and a.size == int(np.prod(shape)):
        c = np.asarray(confidence, dtype=np.float32)
        if c.size * 2 == a.size:
            a = a.reshape(-1, 2)
            a[c.ravel() < MISSING_CONFIDENCE] = 0.0
    return _array(a, shape, "keypoints")


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
    #: Sent again after a restore from a token: its answer was received before and is dropped.
    replay: bool = False


class SessionCore:
    """The session bookkeeping behind :class:`blapose.Session` and its asyncio twin.

    It numbers frames, keeps the frames in flight in order, matches answers to
    them, keeps the latest session token (and the frames answered since it, to
    send again after a restore from it), and after a resume decides which
    in-flight frames the server already processed (answers rebuilt locally),
    which must be sent again, and which answered frames must be sent again
    with their answers dropped (a session restored from a token).
    """

    def __init__(self, joints: int, server_lifter: bool) -> None:
        self.joints = joints
        self.server_lifter = server_lifter
        self.info: Optional[SessionInfo] = None
        self.frames_seen = 0  # processed frames whose answers the client has (received or rebuilt)
        self.server_seen = 0  # processed frames of the attached server's session, as its answers tell
        self.next_index = 0
        self.pending: "list[PendingFrame]" = []
        self.ready: "list[FrameResult]" = []
        self.resumes = 0
        self.recovered = 0
        self.in_a_row = 0  # resumes since the last new answer
        self.token: Optional[SessionToken] = None
        # Frames answered since the token (session frames token.frames_seen ..
        # frames_seen), to send again after a restore from it; empty without a token.
        self.history: "list[PendingFrame]" = []
        self.token_asked = False  # a TokenRequest is on its way

    def attached(self, info: SessionInfo, first: bool) -> None:
        self.info = info
        self.server_seen = info.frames_seen
        if first:
            self.frames_seen = info.frames_seen
            self.next_index = max(self.next_index, info.frames_seen)

    def offer_token(self, token: SessionToken) -> None:
        """Keep ``token`` if it is the latest one usable to restore the session:
        as of a frame answered, and not older than the one kept."""
        base = self.token.frames_seen if self.token is not None else self.frames_seen
        if not base <= token.frames_seen <= self.frames_seen:
            return
        del self.history[: token.frames_seen - base]
        self.token = token
        self.token_asked = False

    def wants_token(self) -> bool:
        """Whether to ask for a fresh token now (many frames answered since the one kept)."""
        if self.token is None or self.token_asked or len(self.history) < TOKEN_REFRESH:
            return False
        self.token_asked = True
        return True

    def _answered(self, frame: PendingFrame) -> None:
        if self.token is not None:
            self.history.append(frame)

    def make_frame(
        self,
        keypoints,
        pose=None,
        confidence=None,
        frame_index: Optional[int] = None,
    ) -> PendingFrame:
        j = self.joints if self.joints > 0 else int(np.asarray(keypoints).size // 2)
        kp = _keypoints(keypoints, confidence, (j, 2))
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

    def answer(self, resp: pb.StreamResponse) -> Union[FrameResult, FrameRejected, None]:
        """Match one stream response to the oldest frame in flight; None for a
        session token (kept) or the answer to a frame sent again (dropped)."""
        kind = resp.WhichOneof("kind")
        if kind == "token":
            assert self.info is not None
            self.offer_token(SessionToken(self.info.session_id, resp.token.frames_seen, resp.token.token))
            return None
        if not self.pending:
            raise ProtocolError(f"got a {kind!r} response with no frame in flight")
        frame = self.pending.pop(0)
        if kind == "frame":
            msg = resp.frame
            if msg.frame_index != frame.frame_index:
                raise ProtocolError(f"answer for frame {msg.frame_index}, expected {frame.frame_index}")
            if msg.frames_seen != self.server_seen + 1:
                raise ProtocolError(f"frames_seen {msg.frames_seen}, expected {self.server_seen + 1}")
            self.server_seen = msg.frames_seen
            if frame.replay:
                return None  # answered before, by the session in the same state
            if msg.frames_seen != self.frames_seen + 1:
                raise ProtocolError(f"frames_seen {msg.frames_seen}, expected {self.frames_seen + 1}")
            self.frames_seen = msg.frames_seen
            self.in_a_row = 0
            self._answered(frame)
            return FrameResult.from_proto(msg)
        if kind == "error":
            msg = resp.error
            if frame.replay:
                raise ProtocolError(
                    f"frame {frame.frame_index}, sent again to the session restored from its token, was "
                    f"refused ({status_code(msg.code).name}: {msg.message}) although it was processed before"
                )
            return FrameRejected(msg.frame_index, status_code(msg.code), msg.message)
        raise ProtocolError(f"expected a frame answer, got {kind!r}")

    def after_resume(self) -> "list[PendingFrame]":
        """Account for the frames in flight when the connection dropped, once
        ``attached`` has stored the resumed session's ``info``; returns the
        frames to send again, in order.

        * Restored from a token behind the answers received (``info.frames_seen``
          below ``frames_seen``): the frames answered since then are sent again
          (marked ``replay``: their answers are dropped), then every frame in flight.
        * Otherwise the first ``info.frames_seen - frames_seen`` frames in flight
          were processed (their answers are rebuilt locally and queued in
          ``ready``) and the rest are sent again. Assumes none of the lost answers
          was a refusal (a refused frame is not counted; see the README).
        """
        info = self.info
        assert info is not None
        self.token_asked = False  # a request on the old stream is lost with it
        fresh = [f for f in self.pending if not f.replay]
        behind = self.frames_seen - info.frames_seen
        if behind > 0:
            base = self.token.frames_seen if self.token is not None else self.frames_seen
            if info.frames_seen < base or len(self.history) != self.frames_seen - base:
                raise ProtocolError(
                    f"resumed session has frames_seen={info.frames_seen}, but {self.frames_seen} were "
                    "answered and the frames since are not known any more"
                )
            again = self.history[info.frames_seen - base :]
            self.pending = [replace(f, replay=True) for f in again] + fresh
            self.resumes += 1
            self.in_a_row += 1
            return list(self.pending)
        processed = -behind
        if processed > len(fresh):
            raise ProtocolError(
                f"resumed session has frames_seen={info.frames_seen}, but {self.frames_seen} were "
                f"answered and {len(fresh)} were in flight"
            )
        lengths = info.bone_lengths
        for i in range(processed):
            f = fresh.pop(0)
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
            self._answered(f)
        self.pending = fresh
        self.recovered += processed
        self.frames_seen = info.frames_seen
        self.resumes += 1
        self.in_a_row += 1
        return list(self.pending)


def resumable(err: RpcError, token: bool = False) -> bool:
    """Whether resuming may help after a stream failed with ``err``.

    Without a session token: a dropped connection (UNAVAILABLE), not a server
    shutting down, whose sessions end with it. With one (``token``), as the
    Rust client's failover: also a server shutting down (its last message was
    a token), UNKNOWN and CANCELLED (a connection dying mid-answer).
    """
    if isinstance(err, Unavailable):
        return token or "shutting down" not in err.details
    return token and isinstance(err, (UnknownError, Cancelled))


def resume_request(session_id: str, token: Optional[SessionToken]) -> pb.StreamRequest:
    """``resume`` with the latest token (restores the session where it is not held)."""
    req = pb.ResumeSession(session_id=session_id, session_tokens=True)
    if token is not None:
        req.session_token = token.token
    return pb.StreamRequest(resume=req)


def subject_proto(height: Optional[float], sex: Optional[str]) -> Optional[pb.Subject]:
    """The ``Subject`` message for a stature in metres and an optional sex
    (``"female"``/``"male"``); None without a stature."""
    if height is None:
        if sex is not None:
            raise ValueError("sex needs the person's height")
        return None
    sexes = {None: pb.SEX_UNSPECIFIED, "female": pb.SEX_FEMALE, "male": pb.SEX_MALE}
    if sex not in sexes:
        raise ValueError(f"sex must be 'female', 'male' or None, got {sex!r}")
    return pb.Subject(height_m=float(height), sex=sexes[sex])


def open_request(
    layout: Layout,
    image_size: Optional[Tuple[int, int]],
    model: Optional[Union[str, int]],
    camera: Optional[Camera],
    server_lifter: bool,
    label: Optional[str],
    subject: Optional[pb.Subject] = None,
    motion: Optional[float] = None,
) -> Tuple[pb.StreamRequest, int]:
    value, joints = layout_value(layout)
    fmt = input_format(value, image_size)
    req = pb.OpenSession(
        input_format=fmt,
        model=model_value(model),  # type: ignore[arg-type]
        client_label=label or "",
        server_lifter=server_lifter,
        session_tokens=True,
    )
    if camera is not None:
        req.camera.CopyFrom(camera.to_proto())
    if subject is not None:
        req.subject.CopyFrom(subject)
    if motion is not None:
        req.motion.CopyFrom(motion_options(motion))
    return pb.StreamRequest(open=req), joints


def motion_options(frame_rate_hz: float) -> pb.MotionOptions:
    """The motion option for a stream or sequence at ``frame_rate_hz`` (0: 50)."""
    return pb.MotionOptions(enabled=True, frame_rate_hz=float(frame_rate_hz))


def sequence_request(
    keypoints,
    poses,
    layout: Layout,
    image_size: Optional[Tuple[int, int]],
    model: Optional[Union[str, int]],
    camera: Optional[Camera],
    confidence,
    subject: Optional[pb.Subject] = None,
    motion: Optional[float] = None,
) -> Tuple[pb.AdjustSequenceRequest, int]:
    value, joints = layout_value(layout)
    kp = np.asarray(keypoints, dtype=np.float32)
    t = int(kp.shape[0]) if kp.ndim >= 1 else 0
    if joints < 0:
        joints = int(kp[0].size // 2) if t else 0
    kp = _keypoints(kp, confidence, (t, joints, 2))
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
    if subject is not None:
        req.subject.CopyFrom(subject)
    if motion is not None:
        req.motion.CopyFrom(motion_options(motion))
    return req, t


def sequence_result(resp: pb.AdjustSequenceResponse, t: int) -> SequenceResult:
    roots = np.asarray(resp.root_positions, dtype=np.float32).reshape(t, 3) if resp.root_positions else None
    world = np.asarray(resp.world_poses_3d, dtype=np.float32).reshape(t, 17, 3) if resp.world_poses_3d else None
    return SequenceResult(
        adjusted=np.asarray(resp.adjusted_poses_3d, dtype=np.float32).reshape(t, 17, 3),
        bone_lengths=np.asarray(resp.bone_lengths, dtype=np.float32).reshape(t, 16),
        model=model_name(resp.model),
        root_positions=roots,
        focal_assumed=resp.focal_assumed,
        world_poses=world,
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
