"""Typed exceptions.

Every error the library raises derives from :class:`BlaposeError`:

* :class:`RpcError` and one subclass per gRPC status code (``InvalidArgument``,
  ``NotFound``, ``ResourceExhausted``, ``Unavailable``, ``Unauthenticated``,
  ``DeadlineExceeded``, ``FailedPrecondition``, ``Aborted``, ``OutOfRange``,
  ``Internal``, ...): a call or a stream ended with that status.
* :class:`FrameRejected`: the server refused ONE frame in-band (a
  ``FrameError``); the session is unchanged and stays usable.
* :class:`ProtocolError`: the server broke the protocol (should not happen).

Local input mistakes (wrong array shapes, NaN) raise :class:`ValueError` before
anything is sent.
"""

from __future__ import annotations

from typing import Dict, Optional, Type
from urllib.parse import unquote

import grpc

__all__ = [
    "BlaposeError",
    "RpcError",
    "Cancelled",
    "UnknownError",
    "InvalidArgument",
    "DeadlineExceeded",
    "NotFound",
    "AlreadyExists",
    "PermissionDenied",
    "ResourceExhausted",
    "FailedPrecondition",
    "Aborted",
    "OutOfRange",
    "Unimplemented",
    "Internal",
    "Unavailable",
    "DataLoss",
    "Unauthenticated",
    "FrameRejected",
    "ProtocolError",
    "from_grpc_error",
]


class BlaposeError(Exception):
    """Base class of every error raised by this package."""


class RpcError(BlaposeError):
    """A gRPC call (or a session's stream) ended with a non-OK status.

    Attributes:
        code: the :class:`grpc.StatusCode`.
        details: the server's message.
    """

    code: grpc.StatusCode = grpc.StatusCode.UNKNOWN

    def __init__(self, details: str, code: Optional[grpc.StatusCode] = None) -> None:
        if code is not None:
            self.code = code
        self.details = details
        super().__init__(f"{self.code.name}: {details}")


class Cancelled(RpcError):
    code = grpc.StatusCode.CANCELLED


class UnknownError(RpcError):
    code = grpc.StatusCode.UNKNOWN


class InvalidArgument(RpcError):
    """Bad request (open/resume request, AdjustSequence input, ...)."""

    code = grpc.StatusCode.INVALID_ARGUMENT


class DeadlineExceeded(RpcError):
    """A deadline passed (the client's timeout, or the server's open timeout)."""

    code = grpc.StatusCode.DEADLINE_EXCEEDED


class NotFound(RpcError):
    """Unknown, expired or closed session id."""

    code = grpc.StatusCode.NOT_FOUND


class AlreadyExists(RpcError):
    code = grpc.StatusCode.ALREADY_EXISTS


class PermissionDenied(RpcError):
    code = grpc.StatusCode.PERMISSION_DENIED


class ResourceExhausted(RpcError):
    """Too many sessions or offline requests on the server."""

    code = grpc.StatusCode.RESOURCE_EXHAUSTED


class FailedPrecondition(RpcError):
    code = grpc.StatusCode.FAILED_PRECONDITION


class Aborted(RpcError):
    """The session was taken over by another stream or closed by CloseSession."""

    code = grpc.StatusCode.ABORTED


class OutOfRange(RpcError):
    """A message over the server's size limit."""

    code = grpc.StatusCode.OUT_OF_RANGE


class Unimplemented(RpcError):
    code = grpc.StatusCode.UNIMPLEMENTED


class Internal(RpcError):
    code = grpc.StatusCode.INTERNAL


class Unavailable(RpcError):
    """The server cannot be reached (or is shutting down)."""

    code = grpc.StatusCode.UNAVAILABLE


class DataLoss(RpcError):
    code = grpc.StatusCode.DATA_LOSS


class Unauthenticated(RpcError):
    """Missing or wrong bearer token."""

    code = grpc.StatusCode.UNAUTHENTICATED


_BY_CODE: Dict[grpc.StatusCode, Type[RpcError]] = {
    cls.code: cls
    for cls in (
        Cancelled,
        UnknownError,
        InvalidArgument,
        DeadlineExceeded,
        NotFound,
        AlreadyExists,
        PermissionDenied,
        ResourceExhausted,
        FailedPrecondition,
        Aborted,
        OutOfRange,
        Unimplemented,
        Internal,
        Unavailable,
        DataLoss,
        Unauthenticated,
    )
}

_BY_NUMBER: Dict[int, grpc.StatusCode] = {c.value[0]: c for c in grpc.StatusCode}


def status_code(number: int) -> grpc.StatusCode:
    """The :class:`grpc.StatusCode` for a numeric code (UNKNOWN if not one)."""
    return _BY_NUMBER.get(number, grpc.StatusCode.UNKNOWN)


#: What the server says when a call's grpc-timeout expires on its side.
_SERVER_TIMEOUT = "Timeout expired"


def from_grpc_error(err: grpc.RpcError) -> RpcError:
    """Turn a ``grpc.RpcError`` (a call's failure) into the typed exception."""
    code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
    details = (err.details() if hasattr(err, "details") else None) or str(err)
    if code == grpc.StatusCode.CANCELLED and _SERVER_TIMEOUT in unquote(details):
        # The call's own deadline ran out, noticed first by the server: it
        # ends the call with CANCELLED "Timeout expired" (tonic), racing the
        # client's DEADLINE_EXCEEDED. Either way it is the caller's deadline.
        code = grpc.StatusCode.DEADLINE_EXCEEDED
    cls = _BY_CODE.get(code, RpcError)
    return cls(details, code)


class FrameRejected(BlaposeError):
    """The server refused one frame in-band (``FrameError``).

    The session state is unchanged (the frame is not counted) and the session
    stays usable. ``code`` is INVALID_ARGUMENT (bad values, e.g. a zero-length
    bone), RESOURCE_EXHAUSTED (server queue full: send it again later) or
    INTERNAL (the model or the server lifter failed on it).

    Attributes:
        frame_index: the frame's index (as sent).
        code: the :class:`grpc.StatusCode`.
        message: the server's explanation.
    """

    def __init__(self, frame_index: int, code: grpc.StatusCode, message: str) -> None:
        self.frame_index = frame_index
        self.code = code
        self.message = message
        super().__init__(f"frame {frame_index} rejected ({code.name}): {message}")


class ProtocolError(BlaposeError):
    """The server's answers broke the blapose.v1 protocol."""
