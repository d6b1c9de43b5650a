"""The asyncio client: :class:`Client` and :class:`Session`, the twins of
:class:`blapose.Client` and :class:`blapose.Session` (same arguments, same
results, same exceptions, same resumption guarantee).

>>> async with blapose.aio.Client("http://127.0.0.1:50051") as client:
...     async with await client.session(layout="coco17", image_size=(1920, 1080)) as s:
...         result = await s.send(keypoints, pose)
...         async for r in s.stream(frames):      # a sync or async iterable
...             ...

Implementation: every call runs the synchronous client on a worker thread of
the client's own executor, so the event loop never blocks and the asyncio and
sync clients behave identically. (``grpc.aio`` is deliberately not used for
sessions: a write that races with the end of a stream makes it report
INTERNAL "Internal error from Core" instead of the real status, e.g. the
UNAVAILABLE of a dropped connection that should be resumed, or the ABORTED
of a takeover.)
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
from pathlib import Path
from types import TracebackType
from typing import Any, AsyncIterator, Callable, Iterable, Iterator, Optional, Sequence, Tuple, Type, TypeVar, Union

from . import _common as c
from . import client as _sync
from .errors import FrameRejected
from .types import (
    ArrayLike,
    Camera,
    ClosedSession,
    FrameResult,
    Layout,
    ModelInfo,
    SequenceResult,
    SessionInfo,
    SessionToken,
)

__all__ = ["Client", "Session"]

T = TypeVar("T")
_DONE = object()


class Client:
    """An asyncio connection to a blapose server (or to several replicas: a
    list of URLs); arguments as :class:`blapose.Client`.

    ``max_workers`` bounds the threads running blocking calls: one per session
    operation in progress (so at least the number of sessions used at once).
    """

    def __init__(
        self,
        url: Union[str, Sequence[str]] = "http://127.0.0.1:50051",
        token: Optional[str] = None,
        tls: Optional[bool] = None,
        ca_cert: Optional[Union[str, bytes, Path]] = None,
        tls_domain: Optional[str] = None,
        timeout: float = 30.0,
        max_workers: int = 256,
    ) -> None:
        self.sync = _sync.Client(url, token=token, tls=tls, ca_cert=ca_cert, tls_domain=tls_domain, timeout=timeout)
        self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=max_workers, thread_name_prefix="blapose")

    async def _run(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._executor, functools.partial(fn, *args, **kwargs))

    async def close(self) -> None:
        """Close the channel and the worker threads."""
        await self._run(self.sync.close)
        self._executor.shutdown(wait=False)

    async def __aenter__(self) -> "Client":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def wait_ready(self, timeout: Optional[float] = None) -> None:
        """Wait until the channel is connected (:class:`Unavailable` after ``timeout``)."""
        await self._run(self.sync.wait_ready, timeout)

    async def info(self) -> ModelInfo:
        """What the server runs (see :meth:`blapose.Client.info`)."""
        return await self._run(self.sync.info)

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
        height: Optional[float] = None,
        sex: Optional[str] = None,
        motion: Optional[float] = None,
    ) -> SequenceResult:
        """Adjust a whole sequence in one call (see :meth:`blapose.Client.adjust_sequence`)."""
        return await self._run(
            self.sync.adjust_sequence,
            keypoints,
            poses,
            layout=layout,
            image_size=image_size,
            model=model,
            camera=camera,
            confidence=confidence,
            height=height,
            sex=sex,
            motion=motion,
        )

    async def close_session(self, session_id: str, *, affinity: Optional[str] = None) -> ClosedSession:
        """Close a session by id (see :meth:`blapose.Client.close_session`)."""
        return await self._run(self.sync.close_session, session_id, affinity=affinity)

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
        max_resumes: int = c.MAX_RESUMES,
        height: Optional[float] = None,
        sex: Optional[str] = None,
        motion: Optional[float] = None,
    ) -> "Session":
        """Open an online session (see :meth:`blapose.Client.session`)."""
        s = await self._run(
            self.sync.session,
            layout,
            image_size,
            model,
            camera,
            server_lifter=server_lifter,
            label=label,
            auto_resume=auto_resume,
            resume_timeout=resume_timeout,
            max_resumes=max_resumes,
            height=height,
            sex=sex,
            motion=motion,
        )
        return Session(self, s)

    async def resume(
        self,
        session_id: str,
        *,
        token: Optional[Union[SessionToken, bytes]] = None,
        affinity: Optional[str] = None,
        auto_resume: bool = True,
        resume_timeout: float = 30.0,
        max_resumes: int = c.MAX_RESUMES,
    ) -> "Session":
        """Re-attach to a detached session by id, or restore it from its token
        (see :meth:`blapose.Client.resume`)."""
        s = await self._run(
            self.sync.resume,
            session_id,
            token=token,
            affinity=affinity,
            auto_resume=auto_resume,
            resume_timeout=resume_timeout,
            max_resumes=max_resumes,
        )
        return Session(self, s)


class Session:
    """An asyncio online session (see :class:`blapose.Session` for the guarantees).

    Use one session from one task at a time.
    """

    def __init__(self, client: Client, session: _sync.Session) -> None:
        self._client = client
        self.sync = session

    @property
    def info(self) -> SessionInfo:
        return self.sync.info

    @property
    def session_id(self) -> str:
        return self.sync.session_id

    @property
    def frames_seen(self) -> int:
        return self.sync.frames_seen

    @property
    def resumes(self) -> int:
        return self.sync.resumes

    @property
    def recovered(self) -> int:
        return self.sync.recovered

    @property
    def token(self) -> Optional[SessionToken]:
        """The latest session token (see :attr:`blapose.Session.token`)."""
        return self.sync.token

    @property
    def affinity(self) -> str:
        """The session's ``blapose-affinity`` key."""
        return self.sync.affinity

    @property
    def url(self) -> str:
        """The URL of the server the session is attached to."""
        return self.sync.url

    async def request_token(self) -> SessionToken:
        """Ask for a session token now (see :meth:`blapose.Session.request_token`)."""
        return await self._client._run(self.sync.request_token)

    async def send(
        self,
        keypoints: ArrayLike,
        pose: Optional[ArrayLike] = None,
        confidence: Optional[ArrayLike] = None,
        frame_index: Optional[int] = None,
    ) -> FrameResult:
        """Send one frame and wait for its answer (see :meth:`blapose.Session.send`)."""
        return await self._client._run(self.sync.send, keypoints, pose, confidence, frame_index)

    async def stream(
        self,
        frames: Union[Iterable, AsyncIterator],
        window: int = 64,
        raise_on_error: bool = True,
    ) -> AsyncIterator[Union[FrameResult, FrameRejected]]:
        """Pipeline frames from a sync or async iterable; yields results in order
        (see :meth:`blapose.Session.stream`)."""
        loop = asyncio.get_running_loop()
        source: Iterable
        if hasattr(frames, "__aiter__"):
            ait = frames.__aiter__()  # type: ignore[union-attr]

            async def anext_item() -> Any:
                return await ait.__anext__()

            def pull() -> Iterator:
                # Runs on the worker thread; the event loop is free meanwhile.
                while True:
                    try:
                        yield asyncio.run_coroutine_threadsafe(anext_item(), loop).result()
                    except StopAsyncIteration:
                        return

            source = pull()
        else:
            source = frames  # type: ignore[assignment]
        gen = self.sync.stream(source, window=window, raise_on_error=raise_on_error)
        try:
            while True:
                item = await self._client._run(next, gen, _DONE)
                if item is _DONE:
                    return
                yield item
        finally:
            await self._client._run(gen.close)

    async def close(self) -> ClosedSession:
        """Close the session for good (see :meth:`blapose.Session.close`)."""
        return await self._client._run(self.sync.close)

    async def detach(self) -> str:
        """End this stream, keep the session for the server's TTL; returns its id."""
        return await self._client._run(self.sync.detach)

    async def __aenter__(self) -> "Session":
        return self

    async def __aexit__(
        self,
        exc_type: Optional[Type[BaseException]],
        exc: Optional[BaseException],
        tb: Optional[TracebackType],
    ) -> None:
        await self._client._run(self.sync.__exit__, exc_type, exc, tb)
