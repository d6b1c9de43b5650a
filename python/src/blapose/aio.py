"""The asyncio client: :class:`Client` and :class:`Session`, the twins of
:class:`blapose.Client` and :class:`blapose.Session` (same arguments, same
results, same exceptions, same resumption guarantee), on ``grpc.aio``.

>>> async with blapose.aio.Client("http://127.0.0.1:50051") as client:
...     async with await client.session(layout="coco17", image_size=(1920, 1080)) as s:
...         result = await s.send(keypoints, pose)
...         async for r in s.stream(frames):
...             ...
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import AsyncIterator, Iterable, Optional, Tuple, Union

import grpc
import grpc.aio

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


class Client:
    """An asyncio connection to a blapose server (see :class:`blapose.Client`).

    Create it inside a running event loop; ``async with`` (or ``await close()``)
    releases the channel.
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
            self._channel = grpc.aio.secure_channel(endpoint.target, c.credentials(ca_cert), options=options)
        else:
            self._channel = grpc.aio.insecure_channel(endpoint.target, options=options)
        self._stub = pb_grpc.PoseAdjustmentStub(self._channel)
        self._metadata = c.metadata(token)

    async def close(self) -> None:
        """Close the channel."""
        await self._channel.close()

    async def __aenter__(self) -> "Client":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def wait_ready(self, timeout: Optional[float] = None) -> None:
        """Wait until the channel is connected (:class:`Unavailable` after ``timeout``)."""
        t = timeout or self.timeout
        try:
            await asyncio.wait_for(self._channel.channel_ready(), t)
        except asyncio.TimeoutError:
            raise Unavailable(f"could not connect to {self.url} within {t} s") from None

    async def _unary(self, method, request):
        try:
            return await method(request, timeout=self.timeout, metadata=self._metadata)
        except grpc.RpcError as e:
            raise from_grpc_error(e) from None

    async def info(self) -> ModelInfo:
        """What the server runs (see :meth:`blapose.Client.info`)."""
        return ModelInfo.from_proto(await self._unary(self._stub.ModelInfo, pb.ModelInfoRequest()))

    async def adjust_sequence(
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
        """Adjust a whole sequence in one call (see :meth:`blapose.Client.adjust_sequence`)."""
        req, t = c.sequence_request(keypoints, poses, layout, image_size, model, camera, confidence)
        return c.sequence_result(await self._unary(self._stub.AdjustSequence, req), t)

    async def close_session(self, session_id: str) -> ClosedSession:
        """Close a session by id (see :meth:`blapose.Client.close_session`)."""
        resp = await self._unary(self._stub.CloseSession, pb.CloseSessionRequest(session_id=session_id))
        return ClosedSession(session_id, resp.frames_seen, _lengths(resp.bone_lengths))

    async def session(
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
        """Open an online session (see :meth:`blapose.Client.session`)."""
        req, joints = c.open_request(layout, image_size, model, camera, server_lifter, label)
        s = Session(self, joints, server_lifter, auto_resume, resume_timeout)
        await s._start(req)
        return s

    async def resume(self, session_id: str, *, auto_resume: bool = True, resume_timeout: float = 30.0) -> "Session":
        """Re-attach to a detached session by id (see :meth:`blapose.Client.resume`)."""
        s = Session(self, -1, False, auto_resume, resume_timeout)
        await s._start(pb.StreamRequest(resume=pb.ResumeSession(session_id=session_id)))
        return s


class Session:
    """An asyncio online session (see :class:`blapose.Session` for the guarantees)."""

    def __init__(
        self, client: Client, joints: int, server_lifter: bool, auto_resume: bool, resume_timeout: float
    ) -> None:
        self._client = client
        self.auto_resume = auto_resume
        self.resume_timeout = resume_timeout
        self._core = c.SessionCore(joints, server_lifter)
        self._failed: Optional[BaseException] = None
        self._done = False
        self._epoch = 0
        self._call: Optional[grpc.aio.StreamStreamCall] = None

    async def _start(self, first: pb.StreamRequest) -> None:
        await self._attach(first)
        if first.WhichOneof("kind") == "resume":
            info = self.info
            self._core.server_lifter = info.lifter is not None
            self._core.joints = LAYOUTS[info.layout][1] if info.layout in LAYOUTS else -1

    @property
    def info(self) -> SessionInfo:
        assert self._core.info is not None
        return self._core.info

    @property
    def session_id(self) -> str:
        return self.info.session_id

    @property
    def frames_seen(self) -> int:
        return self._core.frames_seen

    @property
    def resumes(self) -> int:
        return self._core.resumes

    @property
    def recovered(self) -> int:
        return self._core.recovered

    # -- plumbing --------------------------------------------------------------
    async def _attach(self, first: pb.StreamRequest) -> None:
        call = self._client._stub.Stream(metadata=self._client._metadata)
        try:
            await call.write(first)
            resp = await asyncio.wait_for(call.read(), self._client.timeout)
        except asyncio.TimeoutError:
            call.cancel()
            raise DeadlineExceeded(f"no answer to open/resume within {self._client.timeout} s") from None
        except grpc.RpcError as e:
            raise from_grpc_error(e) from None
        except asyncio.InvalidStateError:
            raise from_grpc_error(await self._status_error(call)) from None
        if resp is grpc.aio.EOF:
            raise from_grpc_error(await self._status_error(call)) from None
        if resp.WhichOneof("kind") != "opened":
            call.cancel()
            raise ProtocolError(f"first response is {resp.WhichOneof('kind')!r}, not 'opened'")
        self._call = call
        self._core.attached(SessionInfo.from_proto(resp.opened), first=self._core.info is None)

    @staticmethod
    async def _status_error(call) -> grpc.RpcError:
        code = await call.code()
        details = await call.details()
        err = grpc.aio.AioRpcError(code, grpc.aio.Metadata(), grpc.aio.Metadata(), details=details)
        return err

    async def _write(self, req: pb.StreamRequest) -> None:
        assert self._call is not None
        try:
            await self._call.write(req)
        except (grpc.RpcError, asyncio.InvalidStateError):
            pass  # the read side reports the failure (and resumes)

    async def _resume(self, cause: RpcError) -> None:
        deadline = time.monotonic() + self.resume_timeout
        if self._call is not None:
            self._call.cancel()
        req = pb.StreamRequest(resume=pb.ResumeSession(session_id=self.session_id))
        delay = 0.05
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise cause
            try:
                await self._client.wait_ready(timeout=remaining)
                await self._attach(req)
                break
            except Unavailable:
                await asyncio.sleep(min(delay, max(0.0, deadline - time.monotonic())))
                delay = min(delay * 2, 1.0)
        for frame in self._core.after_resume(self.info):
            await self._write(frame.request)

    async def _receive(self) -> Union[FrameResult, FrameRejected]:
        while True:
            if self._core.ready:
                return self._core.ready.pop(0)
            assert self._call is not None
            try:
                resp = await self._call.read()
                if resp is grpc.aio.EOF:
                    raise await self._status_error(self._call)
            except grpc.RpcError as e:
                err = from_grpc_error(e)
                if err.code == grpc.StatusCode.OK:
                    self._failed = ProtocolError("the server ended the stream with frames in flight")
                    raise self._failed from None
                if self.auto_resume and c.resumable(err):
                    try:
                        await self._resume(err)
                    except BaseException as e2:
                        self._failed = e2
                        raise
                    continue
                self._failed = err
                raise err from None
            try:
                return self._core.answer(resp)
            except ProtocolError as e:
                self._failed = e
                self._call.cancel()
                raise

    def _check_usable(self) -> None:
        if self._failed is not None:
            raise BlaposeError(f"the session's stream failed earlier: {self._failed}")
        if self._done:
            raise BlaposeError("the session is closed or detached")

    async def _begin(self) -> int:
        self._check_usable()
        self._epoch += 1
        await self._drain()
        return self._epoch

    async def _drain(self) -> None:
        while self._failed is None and (self._core.pending or self._core.ready):
            await self._receive()

    # -- frames ----------------------------------------------------------------
    async def send(
        self,
        keypoints: ArrayLike,
        pose: Optional[ArrayLike] = None,
        confidence: Optional[ArrayLike] = None,
        frame_index: Optional[int] = None,
    ) -> FrameResult:
        """Send one frame and wait for its answer (see :meth:`blapose.Session.send`)."""
        await self._begin()
        frame = self._core.make_frame(keypoints, pose, confidence, frame_index)
        self._core.pending.append(frame)
        await self._write(frame.request)
        result = await self._receive()
        if isinstance(result, FrameRejected):
            raise result
        return result

    async def stream(
        self,
        frames: Union[Iterable, AsyncIterator],
        window: int = 64,
        raise_on_error: bool = True,
    ) -> AsyncIterator[Union[FrameResult, FrameRejected]]:
        """Pipeline frames (a sync or async iterable); yields results in order
        (see :meth:`blapose.Session.stream`)."""
        if window < 1:
            raise ValueError("window must be >= 1")
        epoch = await self._begin()
        ait = frames.__aiter__() if hasattr(frames, "__aiter__") else None
        it = None if ait is not None else iter(frames)  # type: ignore[arg-type]
        exhausted = False
        try:
            while True:
                while not exhausted and len(self._core.pending) < window:
                    try:
                        item = await ait.__anext__() if ait is not None else next(it)  # type: ignore[arg-type]
                    except (StopIteration, StopAsyncIteration):
                        exhausted = True
                        break
                    frame = self._core.make_frame(*c.split_item(item))
                    self._core.pending.append(frame)
                    await self._write(frame.request)
                if not self._core.pending and not self._core.ready:
                    return
                result = await self._receive()
                if isinstance(result, FrameRejected) and raise_on_error:
                    raise result
                yield result
        finally:
            if self._epoch == epoch:
                await self._drain()

    async def close(self) -> ClosedSession:
        """Close the session for good (see :meth:`blapose.Session.close`)."""
        await self._begin()
        self._done = True
        assert self._call is not None
        try:
            await self._call.write(pb.StreamRequest(close=pb.CloseSession()))
            await self._call.done_writing()
            resp = await self._call.read()
            if resp is grpc.aio.EOF:
                raise await self._status_error(self._call)
        except grpc.RpcError as e:
            raise from_grpc_error(e) from None
        if resp.WhichOneof("kind") != "closed":
            raise ProtocolError(f"expected 'closed', got {resp.WhichOneof('kind')!r}")
        msg = resp.closed
        return ClosedSession(msg.session_id, msg.frames_seen, _lengths(msg.bone_lengths))

    async def detach(self) -> str:
        """End this stream, keep the session for the server's TTL; returns its id."""
        if not self._done and self._call is not None:
            self._done = True
            try:
                await self._call.done_writing()
                while await self._call.read() is not grpc.aio.EOF:
                    pass
            except (grpc.RpcError, asyncio.InvalidStateError):
                pass
        return self.session_id

    async def __aenter__(self) -> "Session":
        return self

    async def __aexit__(self, exc_type, exc, tb) -> None:
        if self._done:
            return
        if exc_type is None and self._failed is None:
            await self.close()
            return
        try:
            if self._failed is None:
                await self.close()
            else:
                await self._client.close_session(self.session_id)
        except BlaposeError:
            pass
        finally:
            self._done = True
            if self._call is not None:
                self._call.cancel()
