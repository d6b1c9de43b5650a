"""The synchronous client: :class:`Client` and :class:`Session`."""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path
from types import TracebackType
from typing import Generator, Iterable, Iterator, Optional, Tuple, Type, Union

import grpc

from . import _common as c
from .errors import (
    BlaposeError,
    DeadlineExceeded,
    FrameRejected,
    ProtocolError,
    RpcError,
    Unavailable,
    from_grpc_error,
)
from .types import (
    LAYOUTS,
    ArrayLike,
    Camera,
    ClosedSession,
    FrameResult,
    Layout,
    ModelInfo,
    SequenceResult,
    SessionInfo,
    _lengths,
)
from .v1 import blapose_pb2 as pb
from .v1 import blapose_pb2_grpc as pb_grpc

__all__ = ["Client", "Session"]

_END = object()


class Client:
    """A connection to a blapose server.

    Args:
        url: ``http://host:port`` for plaintext, ``https://host[:port]`` for TLS.
        token: bearer token (the server's ``--auth-token``), sent on every call.
        tls: force TLS on (True) or off (False); default: from the URL scheme.
        ca_cert: PEM bytes or a path of the CA to trust (TLS); default: system roots.
        tls_domain: the name to verify the server certificate against, if not the URL's host.
        timeout: seconds for unary calls and for a session's open/resume answer.

    Use it as a context manager (or call :meth:`close`) to release the channel.
    """

    def __init__(
        self,
        url: str = "http://127.0.0.1:50051",
        token: Optional[str] = None,
        tls: Optional[bool] = None,
        ca_cert: Optional[Union[str, bytes, Path]] = None,
        tls_domain: Optional[str] = None,
        timeout: float = 30.0,
    ) -> None:
        self.url = url
        self.timeout = timeout
        endpoint = c.parse_url(url, tls)
        options = list(c.CHANNEL_OPTIONS)
        if tls_domain:
            options.append(("grpc.ssl_target_name_override", tls_domain))
        if endpoint.tls:
            self._channel = grpc.secure_channel(endpoint.target, c.credentials(ca_cert), options=options)
        else:
            self._channel = grpc.insecure_channel(endpoint.target, options=options)
        self._stub = pb_grpc.PoseAdjustmentStub(self._channel)
        self._metadata = c.metadata(token)

    # -- lifecycle ---------------------------------------------------------
    def close(self) -> None:
        """Close the channel (open sessions' streams end; their sessions stay resumable)."""
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def wait_ready(self, timeout: Optional[float] = None) -> None:
        """Block until the channel is connected (raises :class:`Unavailable` after ``timeout``)."""
        try:
            grpc.channel_ready_future(self._channel).result(timeout=timeout or self.timeout)
        except grpc.FutureTimeoutError:
            raise Unavailable(f"could not connect to {self.url} within {timeout or self.timeout} s") from None

    # -- unary calls -------------------------------------------------------
    def _unary(self, method, request):
        try:
            return method(request, timeout=self.timeout, metadata=self._metadata)
        except grpc.RpcError as e:
            raise from_grpc_error(e) from None

    def info(self) -> ModelInfo:
        """What the server runs: models, weights, layouts, limits (``ModelInfo``)."""
        return ModelInfo.from_proto(self._unary(self._stub.ModelInfo, pb.ModelInfoRequest()))

    def adjust_sequence(
        self,
        keypoints: ArrayLike,
        poses: ArrayLike,
        *,
        layout: Layout,
        image_size: Optional[Tuple[int, int]],
        model: Optional[str] = "bigru",
        camera: Optional[Camera] = None,
        confidence: Optional[ArrayLike] = None,
    ) -> SequenceResult:
        """Adjust a whole sequence in one call (``AdjustSequence``).

        Args:
            keypoints: ``(T, J, 2)`` 2D keypoints in ``layout`` order.
            poses: ``(T, 17, 3)`` lifted 3D poses, metres.
            layout: ``"coco17"``, ``"h36m17"`` or ``"sh16"``.
            image_size: ``(width, height)`` in pixels, or None for normalized keypoints.
            model: ``"bigru"`` (offline, default) or ``"gru"`` (what a stream gives).
            camera: a calibration, to be served by the camera-aware models.
            confidence: optional ``(T, J)`` detector confidences.

        Returns:
            :class:`SequenceResult` with ``adjusted`` (T, 17, 3) and ``bone_lengths`` (T, 16).
        """
        req, t = c.sequence_request(keypoints, poses, layout, image_size, model, camera, confidence)
        return c.sequence_result(self._unary(self._stub.AdjustSequence, req), t)

    def close_session(self, session_id: str) -> ClosedSession:
        """Close a (detached) session by id (``CloseSession``); unknown id: :class:`NotFound`."""
        resp = self._unary(self._stub.CloseSession, pb.CloseSessionRequest(session_id=session_id))
        return ClosedSession(session_id, resp.frames_seen, _lengths(resp.bone_lengths))

    # -- sessions ----------------------------------------------------------
    def session(
        self,
        layout: Layout = "coco17",
        image_size: Optional[Tuple[int, int]] = None,
        model: Optional[str] = None,
        camera: Optional[Camera] = None,
        *,
        server_lifter: bool = False,
        label: Optional[str] = None,
        auto_resume: bool = True,
        resume_timeout: float = 30.0,
    ) -> "Session":
        """Open an online session (a ``Stream`` with ``open``); use it as a context manager.

        Args:
            layout: keypoint layout, ``"coco17"``, ``"h36m17"`` or ``"sh16"``.
            image_size: ``(width, height)`` of the images the pixel keypoints refer to;
                None when the keypoints are already normalized.
            model: None or ``"gru"`` (the only model a stream serves).
            camera: a calibration, to be served by the camera-aware online GRU.
            server_lifter: send keypoints only; the server lifts them (it must run a lifter).
            label: free-form label for the server's logs.
            auto_resume: after a dropped connection, resume the session transparently.
            resume_timeout: how long to keep trying to resume before giving up.

        Raises:
            InvalidArgument: bad layout/image size/model/camera; ResourceExhausted: too
            many sessions; Unauthenticated; Unavailable; DeadlineExceeded.
        """
        req, joints = c.open_request(layout, image_size, model, camera, server_lifter, label)
        return Session(self, req, joints, server_lifter, auto_resume, resume_timeout)

    def resume(
        self,
        session_id: str,
        *,
        auto_resume: bool = True,
        resume_timeout: float = 30.0,
    ) -> "Session":
        """Re-attach to a detached session by id; continue from ``session.info.frames_seen``.

        Unknown/expired/closed id: :class:`NotFound`.
        """
        req = pb.StreamRequest(resume=pb.ResumeSession(session_id=session_id))
        return Session(self, req, -1, False, auto_resume, resume_timeout)


class _Attachment:
    """One ``Stream`` call: a request iterator fed from a queue, and its responses."""

    def __init__(self, client: Client, first: pb.StreamRequest) -> None:
        self._q: "queue.Queue[object]" = queue.Queue()
        self._q.put(first)
        self.call = client._stub.Stream(self._requests(), metadata=client._metadata)

    def _requests(self) -> Iterator[pb.StreamRequest]:
        while True:
            item = self._q.get()
            if item is _END:
                return
            yield item  # type: ignore[misc]

    def send(self, req: pb.StreamRequest) -> None:
        self._q.put(req)

    def end(self) -> None:
        self._q.put(_END)

    def next(self) -> pb.StreamResponse:
        return next(self.call)

    def cancel(self) -> None:
        self.end()
        self.call.cancel()


class Session:
    """An online session: frames in, adjusted poses out, in order.

    Create it with :meth:`Client.session` (or :meth:`Client.resume`). ``send`` does
    one frame at a time; ``stream`` pipelines many. Leaving the ``with`` block
    closes the session (``close``); ``detach`` ends the stream but keeps the
    session on the server for its TTL (resume it with :meth:`Client.resume`).

    Resumption (``auto_resume=True``): when the connection drops (UNAVAILABLE,
    other than a server shutting down), the session re-attaches with ``resume``
    and continues from ``SessionOpened.frames_seen``. Every frame you passed is
    counted in the session exactly once and gets exactly one result, in order:
    frames the server had not processed are sent again; frames it processed
    but whose answers were lost are answered locally with ``recovered=True``:
    their ``bone_lengths`` are the resumed session's estimate (exact for the
    last lost frame, the estimate after it for earlier ones) and ``adjusted``
    is the frame's pose rebuilt with those lengths (``blapose.adjust_pose``; NaN
    in server-lifter sessions, whose lifted pose is not known). This assumes no
    lost answer was an in-band refusal (a refused frame is not counted, and
    the protocol cannot tell which lost frame it was).
    """

    def __init__(
        self,
        client: Client,
        first: pb.StreamRequest,
        joints: int,
        server_lifter: bool,
        auto_resume: bool,
        resume_timeout: float,
    ) -> None:
        self._client = client
        self.auto_resume = auto_resume
        self.resume_timeout = resume_timeout
        self._core = c.SessionCore(joints, server_lifter)
        self._failed: Optional[BaseException] = None
        self._done = False
        self._epoch = 0
        self._att = self._attach(first)
        info = self._core.info
        assert info is not None
        if first.WhichOneof("kind") == "resume":
            # a resumed session keeps its input format and lifter
            self._core.server_lifter = info.lifter is not None
            self._core.joints = LAYOUTS[info.layout][1] if info.layout in LAYOUTS else -1

    # -- properties ----------------------------------------------------------
    @property
    def info(self) -> SessionInfo:
        """The server's ``SessionOpened`` for the current attachment."""
        assert self._core.info is not None
        return self._core.info

    @property
    def session_id(self) -> str:
        return self.info.session_id

    @property
    def frames_seen(self) -> int:
        """Frames the session has processed (as far as answers and resumes tell)."""
        return self._core.frames_seen

    @property
    def resumes(self) -> int:
        """How many times the session re-attached after a dropped connection."""
        return self._core.resumes

    @property
    def recovered(self) -> int:
        """Frames whose answers were lost and rebuilt locally (``recovered=True``)."""
        return self._core.recovered

    # -- stream plumbing -----------------------------------------------------
    def _attach(self, first: pb.StreamRequest) -> _Attachment:
        att = _Attachment(self._client, first)
        timed_out = threading.Event()

        def expire() -> None:
            timed_out.set()
            att.cancel()

        timer = threading.Timer(self._client.timeout, expire)
        timer.daemon = True
        timer.start()
        try:
            resp = att.next()
        except grpc.RpcError as e:
            att.end()
            if timed_out.is_set():
                raise DeadlineExceeded(f"no answer to open/resume within {self._client.timeout} s") from None
            raise from_grpc_error(e) from None
        except StopIteration:
            raise ProtocolError("the stream ended before SessionOpened") from None
        finally:
            timer.cancel()
        if resp.WhichOneof("kind") != "opened":
            att.cancel()
            raise ProtocolError(f"first response is {resp.WhichOneof('kind')!r}, not 'opened'")
        info = SessionInfo.from_proto(resp.opened)
        self._core.attached(info, first=self._core.info is None)
        return att

    def _begin(self) -> int:
        """Start a send/stream/close: answers to frames of an abandoned stream() are read and dropped."""
        self._check_usable()
        self._epoch += 1
        self._drain()
        return self._epoch

    def _drain(self) -> None:
        while self._failed is None and (self._core.pending or self._core.ready):
            self._receive()

    def _check_usable(self) -> None:
        if self._failed is not None:
            raise BlaposeError(f"the session's stream failed earlier: {self._failed}")
        if self._done:
            raise BlaposeError("the session is closed or detached")

    def _resume(self, cause: RpcError) -> None:
        deadline = time.monotonic() + self.resume_timeout
        self._att.cancel()
        req = pb.StreamRequest(resume=pb.ResumeSession(session_id=self.session_id))
        delay = 0.05
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise cause
            try:
                self._client.wait_ready(timeout=remaining)
                self._att = self._attach(req)
                break
            except Unavailable:
                time.sleep(min(delay, max(0.0, deadline - time.monotonic())))
                delay = min(delay * 2, 1.0)
        for frame in self._core.after_resume():
            self._att.send(frame.request)

    def _receive(self) -> Union[FrameResult, FrameRejected]:
        while True:
            if self._core.ready:
                return self._core.ready.pop(0)
            try:
                resp = self._att.next()
            except grpc.RpcError as e:
                err = from_grpc_error(e)
                if self.auto_resume and c.resumable(err):
                    try:
                        self._resume(err)
                    except BaseException as e2:
                        self._failed = e2
                        raise
                    continue
                self._failed = err
                raise err from None
            except StopIteration:
                self._failed = ProtocolError("the server ended the stream with frames in flight")
                raise self._failed from None
            try:
                return self._core.answer(resp)
            except ProtocolError as e:
                self._failed = e
                self._att.cancel()
                raise

    # -- frames --------------------------------------------------------------
    def send(
        self,
        keypoints: ArrayLike,
        pose: Optional[ArrayLike] = None,
        confidence: Optional[ArrayLike] = None,
        frame_index: Optional[int] = None,
    ) -> FrameResult:
        """Send one frame and wait for its answer.

        Args:
            keypoints: ``(J, 2)`` 2D keypoints (pixels, or normalized).
            pose: ``(17, 3)`` lifted pose in metres (None in a server-lifter session).
            confidence: optional ``(J,)`` detector confidences.
            frame_index: echoed back; default: one more than the previous frame's.

        Raises:
            FrameRejected: the server refused this frame (the session is unchanged).
            ValueError: wrong shapes or non-finite values (nothing was sent).
        """
        self._begin()
        frame = self._core.make_frame(keypoints, pose, confidence, frame_index)
        self._core.pending.append(frame)
        self._att.send(frame.request)
        result = self._receive()
        if isinstance(result, FrameRejected):
            raise result
        return result

    def stream(
        self,
        frames: Iterable,
        window: int = 64,
        raise_on_error: bool = True,
    ) -> Generator[Union[FrameResult, FrameRejected], None, None]:
        """Pipeline frames: yields one result per frame, in order.

        Args:
            frames: an iterable (consumed lazily) of ``(keypoints, pose)`` or
                ``(keypoints, pose, confidence)`` tuples; bare keypoints in a
                server-lifter session.
            window: frames in flight at most (the server reads 64 per stream by default).
            raise_on_error: raise :class:`FrameRejected` for a refused frame (default),
                or yield the exception object in its place and go on.

        Frame indices continue from the previous frame's. If you stop iterating
        early, the answers to frames already in flight are read and dropped so
        the session stays usable.
        """
        if window < 1:
            raise ValueError("window must be >= 1")
        epoch = self._begin()
        it = iter(frames)
        exhausted = False
        try:
            while True:
                while not exhausted and len(self._core.pending) < window:
                    try:
                        item = next(it)
                    except StopIteration:
                        exhausted = True
                        break
                    frame = self._core.make_frame(*c.split_item(item))
                    self._core.pending.append(frame)
                    self._att.send(frame.request)
                if not self._core.pending and not self._core.ready:
                    return
                result = self._receive()
                if isinstance(result, FrameRejected) and raise_on_error:
                    raise result
                yield result
        finally:
            if self._epoch == epoch:
                self._drain()

    # -- ending ----------------------------------------------------------------
    def close(self) -> ClosedSession:
        """Close the session for good (``close``): frames_seen and final lengths."""
        self._begin()
        self._done = True
        self._att.send(pb.StreamRequest(close=pb.CloseSession()))
        self._att.end()
        try:
            resp = self._att.next()
        except grpc.RpcError as e:
            raise from_grpc_error(e) from None
        except StopIteration:
            raise ProtocolError("the stream ended without SessionClosed") from None
        if resp.WhichOneof("kind") != "closed":
            raise ProtocolError(f"expected 'closed', got {resp.WhichOneof('kind')!r}")
        msg = resp.closed
        return ClosedSession(
            msg.session_id,
            msg.frames_seen,
            _lengths(msg.bone_lengths),
        )

    def detach(self) -> str:
        """End this stream but keep the session (for the server's TTL); returns its id."""
        if not self._done:
            self._done = True
            self._att.end()
            try:
                for _ in self._att.call:
                    pass
            except grpc.RpcError:
                pass
        return self.session_id

    def __enter__(self) -> "Session":
        return self

    def __exit__(
        self,
        exc_type: Optional[Type[BaseException]],
        exc: Optional[BaseException],
        tb: Optional[TracebackType],
    ) -> None:
        if self._done:
            return
        if exc_type is None and self._failed is None:
            self.close()
            return
        # Leaving on an error: try to close, never mask the original exception.
        try:
            if self._failed is None:
                self.close()
            else:
                self._client.close_session(self.session_id)
        except BlaposeError:
            pass
        finally:
            self._done = True
            self._att.cancel()
