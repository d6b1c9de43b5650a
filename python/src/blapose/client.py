"""The synchronous client: :class:`Client` and :class:`Session`."""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path
from types import TracebackType
from typing import Dict, Generator, Iterable, Iterator, List, Optional, Sequence, Tuple, Type, Union

import grpc

from . import _common as c
from .errors import (
    BlaposeError,
    Cancelled,
    DeadlineExceeded,
    FailedPrecondition,
    FrameRejected,
    NotFound,
    ProtocolError,
    RpcError,
    Unavailable,
    UnknownError,
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
    SessionToken,
    _lengths,
)
from .v1 import blapose_pb2 as pb
from .v1 import blapose_pb2_grpc as pb_grpc

__all__ = ["Client", "Session"]

_END = object()


Metadata = Tuple[Tuple[str, str], ...]


class Client:
    """A connection to a blapose server, or to several replicas of one.

    Args:
        url: ``http://host:port`` for plaintext, ``https://host[:port]`` for TLS;
            or a list of such URLs, replicas sharing a ``--session-key``: calls
            go to the first that answers, and a session whose server goes away
            resumes on another one from its latest session token (see
            :class:`Session`).
        token: bearer token (the server's ``--auth-token``), sent on every call.
        tls: force TLS on (True) or off (False); default: from the URL scheme.
        ca_cert: PEM bytes or a path of the CA to trust (TLS); default: system roots.
        tls_domain: the name to verify the server certificate against, if not the URL's host.
        timeout: seconds for unary calls and for a session's open/resume answer.

    Use it as a context manager (or call :meth:`close`) to release the channels.
    """

    def __init__(
        self,
        url: Union[str, Sequence[str]] = "http://127.0.0.1:50051",
        token: Optional[str] = None,
        tls: Optional[bool] = None,
        ca_cert: Optional[Union[str, bytes, Path]] = None,
        tls_domain: Optional[str] = None,
        timeout: float = 30.0,
    ) -> None:
        #: Every server URL, in the order they are tried.
        self.urls: List[str] = c.urls(url)
        #: The first server URL.
        self.url = self.urls[0]
        self.timeout = timeout
        options = list(c.CHANNEL_OPTIONS)
        if tls_domain:
            options.append(("grpc.ssl_target_name_override", tls_domain))
        self._channels: List[grpc.Channel] = []
        for u in self.urls:
            endpoint = c.parse_url(u, tls)
            if endpoint.tls:
                channel = grpc.secure_channel(endpoint.target, c.credentials(ca_cert), options=options)
            else:
                channel = grpc.insecure_channel(endpoint.target, options=options)
            self._channels.append(channel)
        self._stubs = [pb_grpc.PoseAdjustmentStub(ch) for ch in self._channels]
        self._channel = self._channels[0]
        self._stub = self._stubs[0]
        self._current = 0  # the server the last successful call went to: tried first
        self._metadata: Metadata = c.metadata(token)

    # -- lifecycle ---------------------------------------------------------
    def close(self) -> None:
        """Close the channels (open sessions' streams end; their sessions stay resumable)."""
        for ch in self._channels:
            ch.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _order(self, first: Optional[int] = None) -> List[int]:
        """Server indices, ``first`` (default: the current one) first, then the others in order."""
        n = len(self._stubs)
        start = self._current if first is None else first
        return [(start + k) % n for k in range(n)]

    def _wait_ready(self, i: int, timeout: float) -> None:
        ready = grpc.channel_ready_future(self._channels[i])
        try:
            ready.result(timeout=timeout)
        except grpc.FutureTimeoutError:
            ready.cancel()  # stops its connectivity polling
            raise Unavailable(f"could not connect to {self.urls[i]} within {timeout:g} s") from None

    def wait_ready(self, timeout: Optional[float] = None) -> None:
        """Block until a channel is connected (raises :class:`Unavailable` after ``timeout``).

        With several servers, they are tried in turn (the current one first) and
        the first connected one becomes the current one.
        """
        total = timeout or self.timeout
        if len(self._stubs) == 1:
            try:
                self._wait_ready(0, total)
            except Unavailable:
                raise Unavailable(f"could not connect to {self.url} within {total} s") from None
            return
        deadline = time.monotonic() + total
        while True:
            for i in self._order():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise Unavailable(f"could not connect to any of {self.urls} within {total} s")
                try:
                    self._wait_ready(i, min(remaining, 0.5))
                except Unavailable:
                    continue
                self._current = i
                return

    # -- unary calls -------------------------------------------------------
    def _unary(self, name: str, request, metadata: Optional[Metadata] = None, first: Optional[int] = None):
        """Call ``name`` on the current server; on UNAVAILABLE, on the next ones in turn."""
        last: Optional[RpcError] = None
        for i in self._order(first):
            try:
                resp = getattr(self._stubs[i], name)(
                    request, timeout=self.timeout, metadata=self._metadata if metadata is None else metadata
                )
            except grpc.RpcError as e:
                err = from_grpc_error(e)
                if isinstance(err, Unavailable):
                    last = err
                    continue
                raise err from None
            self._current = i
            return resp
        assert last is not None
        raise last

    def info(self) -> ModelInfo:
        """What the server runs: models, weights, layouts, limits (``ModelInfo``)."""
        return ModelInfo.from_proto(self._unary("ModelInfo", pb.ModelInfoRequest()))

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
        height: Optional[float] = None,
        sex: Optional[str] = None,
        motion: Optional[float] = None,
    ) -> SequenceResult:
        """Adjust a whole sequence in one call (``AdjustSequence``).

        Args:
            keypoints: ``(T, J, 2)`` 2D keypoints in ``layout`` order.
            poses: ``(T, 17, 3)`` lifted 3D poses, metres.
            layout: ``"coco17"``, ``"h36m17"`` or ``"sh16"``.
            image_size: ``(width, height)`` in pixels, or None for normalized keypoints.
            model: ``"bigru"`` (offline, default) or ``"gru"`` (what a stream gives).
            camera: a calibration, to be served by the camera-aware models.
            confidence: optional ``(T, J)`` detector confidences (below
                :data:`blapose.MISSING_CONFIDENCE` a joint is missing).
            height: the person's stature in metres (1.0 to 2.3): every frame then
                gets the stature regression's lengths for it.
            sex: ``"female"`` or ``"male"``, with ``height``.
            motion: the input's frames per second (0 for 50) to run the server's offline
                motion stage: directions smoothed, the pelvis placed
                (``root_positions``), planted feet held.

        Returns:
            :class:`SequenceResult` with ``adjusted`` (T, 17, 3) and ``bone_lengths`` (T, 16).
        """
        req, t = c.sequence_request(
            keypoints, poses, layout, image_size, model, camera, confidence, c.subject_proto(height, sex), motion
        )
        return c.sequence_result(self._unary("AdjustSequence", req), t)

    def _close_session(self, session_id: str, metadata: Metadata, first: Optional[int] = None) -> ClosedSession:
        """``CloseSession`` on each server in turn until one holds the session."""
        req = pb.CloseSessionRequest(session_id=session_id)
        missing: Optional[RpcError] = None
        for i in self._order(first):
            try:
                resp = self._stubs[i].CloseSession(req, timeout=self.timeout, metadata=metadata)
            except grpc.RpcError as e:
                err = from_grpc_error(e)
                if isinstance(err, (NotFound, Unavailable)):
                    missing = err if missing is None or isinstance(err, NotFound) else missing
                    continue
                raise err from None
            return ClosedSession(session_id, resp.frames_seen, _lengths(resp.bone_lengths))
        assert missing is not None
        raise missing

    def close_session(self, session_id: str, *, affinity: Optional[str] = None) -> ClosedSession:
        """Close a (detached) session by id (``CloseSession``); unknown id: :class:`NotFound`.

        With several servers, each is asked in turn until one holds the session.
        ``affinity``: the session's :attr:`Session.affinity` (sent as the
        ``blapose-affinity`` header, so a load balancer routes the call to the
        replica holding the session).
        """
        return self._close_session(session_id, self._session_metadata(affinity))

    def _session_metadata(self, affinity: Optional[str]) -> Metadata:
        if not affinity:
            return self._metadata
        return self._metadata + ((c.AFFINITY_HEADER, affinity),)

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
        max_resumes: int = c.MAX_RESUMES,
        height: Optional[float] = None,
        sex: Optional[str] = None,
        motion: Optional[float] = None,
    ) -> "Session":
        """Open an online session (a ``Stream`` with ``open``); use it as a context manager.

        With several servers, the session opens on the first one that answers.

        Args:
            layout: keypoint layout, ``"coco17"``, ``"h36m17"`` or ``"sh16"``.
            image_size: ``(width, height)`` of the images the pixel keypoints refer to;
                None when the keypoints are already normalized.
            model: None or ``"gru"`` (the only model a stream serves).
            camera: a calibration, to be served by the camera-aware online GRU.
            server_lifter: send keypoints only; the server lifts them (it must run a lifter).
            label: free-form label for the server's logs.
            auto_resume: after a dropped connection (or, with a session token, a
                server gone away), resume the session transparently.
            resume_timeout: how long to keep trying to resume before giving up.
            max_resumes: give up after this many resumes in a row with no new
                answer in between (the stream's error is raised).
            height: the person's stature in metres (1.0 to 2.3): the session then
                answers with the stature regression's lengths for it.
            sex: ``"female"`` or ``"male"``, with ``height``.
            motion: the stream's frames per second (0 for 50) to run the server's causal
                motion stage: directions smoothed (a learned refiner in server-lifter
                sessions), the pelvis placed in camera space (``FrameResult.root``).

        Raises:
            InvalidArgument: bad layout/image size/model/camera/motion; ResourceExhausted: too
            many sessions; Unauthenticated; Unavailable; DeadlineExceeded.
        """
        req, joints = c.open_request(
            layout, image_size, model, camera, server_lifter, label, c.subject_proto(height, sex), motion
        )
        return Session(self, req, joints, server_lifter, auto_resume, resume_timeout, None, max_resumes)

    def resume(
        self,
        session_id: str,
        *,
        token: Optional[Union[SessionToken, bytes]] = None,
        affinity: Optional[str] = None,
        auto_resume: bool = True,
        resume_timeout: float = 30.0,
        max_resumes: int = c.MAX_RESUMES,
    ) -> "Session":
        """Re-attach to a detached session by id; continue from ``session.info.frames_seen``.

        Args:
            session_id: the session's id.
            token: its latest :class:`SessionToken` (:attr:`Session.token`), or the
                token's bytes: a server that does not hold the session (another
                replica with the same ``--session-key``, or the same server after a
                restart) restores it from the token, as of ``token.frames_seen``.
            affinity: the session's :attr:`Session.affinity` key, so a load balancer
                routes the resume to the replica holding it; default: a new key.

        With several servers, each is tried in turn until one resumes the session.
        Unknown/expired/closed id (and no token): :class:`NotFound`; a token made
        under another session key: :class:`Unauthenticated`; for other weights (or
        a server without a key): :class:`FailedPrecondition`.
        """
        if isinstance(token, (bytes, bytearray)):
            token = SessionToken(session_id, -1, bytes(token))
        req = c.resume_request(session_id, token)
        return Session(self, req, -1, False, auto_resume, resume_timeout, affinity, max_resumes)


class _Attachment:
    """One ``Stream`` call: a request iterator fed from a queue, and its responses."""

    def __init__(self, stub: pb_grpc.PoseAdjustmentStub, first: pb.StreamRequest, metadata: Metadata) -> None:
        self._q: "queue.Queue[object]" = queue.Queue()
        self._q.put(first)
        self.call = stub.Stream(self._requests(), metadata=metadata)

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

    Every call of the session (its streams, its resumes, its close) carries the
    gRPC header ``blapose-affinity: <affinity>``, a random key made when the
    session opened, so a load balancer hashing on it keeps the session on one
    replica.

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

    Failover with session tokens: sessions always ask for tokens; a server
    started with ``--session-key`` sends them (see :attr:`token`). While the
    session holds one, it also resumes after its server went away (shut down,
    crashed, unreachable: UNAVAILABLE, UNKNOWN, CANCELLED, or the stream ending
    early), trying its current server first and then the client's other
    servers in order, with the latest token: a replica that does not hold the
    session restores it from the token, the frames answered since the token are
    sent again (their answers, identical, are dropped), and the frames in
    flight follow. If the server holding the session processed frames whose
    answers were lost, the session is closed there and restored from the token,
    so every frame gets its real answer (none ``recovered``). The answers equal
    those of an uninterrupted session. It gives up after ``max_resumes`` resumes
    in a row without a new answer, or when no server resumed it within
    ``resume_timeout`` (raising a server's refusal, e.g. :class:`Unauthenticated`
    for a replica with another key, or else the stream's error).
    """

    def __init__(
        self,
        client: Client,
        first: pb.StreamRequest,
        joints: int,
        server_lifter: bool,
        auto_resume: bool,
        resume_timeout: float,
        affinity: Optional[str] = None,
        max_resumes: int = c.MAX_RESUMES,
    ) -> None:
        self._client = client
        self.auto_resume = auto_resume
        self.resume_timeout = resume_timeout
        self.max_resumes = max_resumes
        self._affinity = affinity or c.new_affinity()
        self._metadata = client._session_metadata(self._affinity)
        self._core = c.SessionCore(joints, server_lifter)
        self._failed: Optional[BaseException] = None
        self._done = False
        self._epoch = 0
        att, info, token, i = self._first_attach(first)
        self._att = att
        self._target = i
        client._current = i
        self._core.attached(info, first=True)
        if token is not None:
            self._core.offer_token(token)
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

    @property
    def token(self) -> Optional[SessionToken]:
        """The latest session token as of a frame answered (None from a server
        without ``--session-key``): resume the session anywhere with it
        (:meth:`Client.resume`). Tokens arrive on open/resume, every
        ``--token-every`` frames, on :meth:`request_token`, and when the server
        shuts down."""
        return self._core.token

    @property
    def affinity(self) -> str:
        """The session's affinity key (the ``blapose-affinity`` header of its calls)."""
        return self._affinity

    @property
    def url(self) -> str:
        """The URL of the server the session is attached to."""
        return self._client.urls[self._target]

    # -- stream plumbing -----------------------------------------------------
    def _first_attach(
        self, first: pb.StreamRequest
    ) -> Tuple[_Attachment, SessionInfo, Optional[SessionToken], int]:
        """Open/resume on the client's servers in turn; a second round if one was unreachable
        (a connection that has just dropped can fail the first call on it, "Stream removed")."""
        last: Optional[RpcError] = None
        for round_ in range(2):
            unreachable = False
            for i in self._client._order():
                try:
                    att, info, token = self._attach(i, first)
                except Unavailable as e:
                    unreachable = True
                    last = last if isinstance(last, NotFound) else e
                    continue
                except NotFound as e:  # (resume) not held there
                    last = e
                    continue
                return att, info, token, i
            if not unreachable:
                break
            if round_ == 0:
                time.sleep(0.1)
        assert last is not None
        raise last

    def _attach(
        self, target: int, first: pb.StreamRequest
    ) -> Tuple[_Attachment, SessionInfo, Optional[SessionToken]]:
        """Open a stream to server ``target`` and read its ``SessionOpened``."""
        att = _Attachment(self._client._stubs[target], first, self._metadata)
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
        token = None
        if resp.opened.session_token:
            token = SessionToken(info.session_id, info.frames_seen, resp.opened.session_token)
        return att, info, token

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

    def _resume_at(self, i: int) -> Optional[Tuple[_Attachment, SessionInfo, Optional[SessionToken]]]:
        """Resume on server ``i`` at a frame already answered or the next one (None: not there)."""
        token = self._core.token
        req = c.resume_request(self.session_id, token)
        att, info, opened_token = self._attach(i, req)
        if token is None or info.frames_seen <= self._core.frames_seen:
            return att, info, opened_token
        # Held there, ahead of the answers received (answers lost in flight):
        # close it there and restore it from the token, as of a frame answered.
        att.cancel()
        try:
            self._client._close_session(self.session_id, self._metadata, first=i)
            att, info, opened_token = self._attach(i, req)
        except RpcError:
            return None
        if info.frames_seen > self._core.frames_seen:
            att.cancel()
            return None
        return att, info, opened_token

    def _resume(self, cause: BaseException) -> None:
        if self._core.in_a_row >= self.max_resumes:
            raise cause
        deadline = time.monotonic() + self.resume_timeout
        self._att.cancel()
        servers = len(self._client._stubs)
        refused: Dict[int, RpcError] = {}
        delay = 0.05
        while True:
            for i in self._client._order(self._target):
                if i in refused:
                    continue
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                try:
                    # No waiting for a server that is down: the call fails fast
                    # (UNAVAILABLE) and the next server is tried, or the round
                    # repeats after a short backoff.
                    got = self._resume_at(i)
                except (Unavailable, DeadlineExceeded, UnknownError, Cancelled):
                    continue
                except RpcError as e:
                    refused[i] = e  # NotFound, Unauthenticated, FailedPrecondition, ...
                    continue
                if got is None:
                    continue
                att, info, token = got
                self._att = att
                self._target = i
                self._core.attached(info, first=False)
                for frame in self._core.after_resume():
                    att.send(frame.request)
                if token is not None:
                    self._core.offer_token(token)
                return
            remaining = deadline - time.monotonic()
            if remaining <= 0 or len(refused) == servers:
                if refused:
                    raise list(refused.values())[-1]
                raise cause
            time.sleep(min(delay, remaining))
            delay = min(delay * 2, 1.0)

    def _recover(self, err: BaseException) -> None:
        """After the stream failed with ``err``: resume, or mark the session failed and raise."""
        failover = self._core.token is not None
        if self.auto_resume and (
            c.resumable(err, failover) if isinstance(err, RpcError) else failover and isinstance(err, ProtocolError)
        ):
            try:
                self._resume(err)
            except BaseException as e2:
                self._failed = e2
                raise
            return
        self._failed = err
        raise err

    def _next_response(self) -> Optional[pb.StreamResponse]:
        """The next response on the stream; None after a resume."""
        try:
            return self._att.next()
        except grpc.RpcError as e:
            err: BaseException = from_grpc_error(e)
        except StopIteration:
            err = ProtocolError("the server ended the stream with frames in flight")
        self._recover(err)
        return None

    def _receive(self) -> Union[FrameResult, FrameRejected]:
        while True:
            if self._core.ready:
                return self._core.ready.pop(0)
            resp = self._next_response()
            if resp is None:
                continue
            try:
                result = self._core.answer(resp)
            except ProtocolError as e:
                self._failed = e
                self._att.cancel()
                raise
            if result is not None:
                return result

    # -- frames --------------------------------------------------------------
    def _send_frame(self, frame: c.PendingFrame) -> None:
        self._core.pending.append(frame)
        self._att.send(frame.request)
        if self._core.wants_token():
            self._att.send(pb.StreamRequest(token_request=pb.TokenRequest()))

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
        self._send_frame(self._core.make_frame(keypoints, pose, confidence, frame_index))
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
                    self._send_frame(self._core.make_frame(*c.split_item(item)))
                if not self._core.pending and not self._core.ready:
                    return
                result = self._receive()
                if isinstance(result, FrameRejected) and raise_on_error:
                    raise result
                yield result
        finally:
            if self._epoch == epoch:
                self._drain()

    def request_token(self) -> SessionToken:
        """Ask the server for a session token as of every frame answered so far
        (``TokenRequest``); it becomes :attr:`token`.

        Raises:
            FailedPrecondition: the server has no ``--session-key``.
        """
        self._begin()
        while True:
            self._att.send(pb.StreamRequest(token_request=pb.TokenRequest()))
            while True:
                resp = self._next_response()
                if resp is None:  # resumed: answer the frames sent again, then ask again
                    self._drain()
                    break
                kind = resp.WhichOneof("kind")
                if kind == "token":
                    self._core.answer(resp)
                    token = self._core.token
                    if token is not None and resp.token.frames_seen == self._core.frames_seen:
                        return token
                elif kind == "error":
                    raise FailedPrecondition(
                        f"the server sends no session token: {resp.error.message}",
                        grpc.StatusCode.FAILED_PRECONDITION,
                    )
                else:
                    self._failed = ProtocolError(f"expected a session token, got {kind!r}")
                    self._att.cancel()
                    raise self._failed

    # -- ending ----------------------------------------------------------------
    def close(self) -> ClosedSession:
        """Close the session for good (``close``): frames_seen and final lengths."""
        self._begin()
        self._done = True
        while True:
            self._att.send(pb.StreamRequest(close=pb.CloseSession()))
            self._att.end()
            try:
                resp = self._att.next()
                while resp.WhichOneof("kind") == "token":
                    resp = self._att.next()
            except grpc.RpcError as e:
                err = from_grpc_error(e)
                if self.auto_resume and self._core.token is not None and c.resumable(err, True):
                    # The server went away: close the session where it resumes.
                    self._recover(err)
                    self._drain()
                    continue
                raise err from None
            except StopIteration:
                raise ProtocolError("the stream ended without SessionClosed") from None
            break
        if resp.WhichOneof("kind") != "closed":
            raise ProtocolError(f"expected 'closed', got {resp.WhichOneof('kind')!r}")
        msg = resp.closed
        return ClosedSession(
            msg.session_id,
            msg.frames_seen,
            _lengths(msg.bone_lengths),
        )

    def detach(self) -> str:
        """End this stream but keep the session (for the server's TTL); returns its id.

        Resume it later with ``client.resume(id, token=session.token,
        affinity=session.affinity)``.
        """
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
                self._client._close_session(self.session_id, self._metadata, first=self._target)
        except BlaposeError:
            pass
        finally:
            self._done = True
            self._att.cancel()
