"""Error paths the real server never takes: a scripted in-process server that breaks
the protocol, refuses frames with every in-band code, or never answers the open."""

from __future__ import annotations

import threading
from concurrent import futures
from typing import Callable, Iterator

import grpc
import numpy as np
import pytest

import blapose
from blapose.v1 import blapose_pb2 as pb
from blapose.v1 import blapose_pb2_grpc as pb_grpc

KP = np.zeros((17, 2))
POSE = np.arange(51, dtype=np.float32).reshape(17, 3) * 0.01

Script = Callable[[Iterator[pb.StreamRequest], grpc.ServicerContext], Iterator[pb.StreamResponse]]


def opened(frames_seen: int = 0, lengths=()) -> pb.StreamResponse:
    return pb.StreamResponse(
        opened=pb.SessionOpened(
            session_id="a" * 32,
            frames_seen=frames_seen,
            bone_lengths=list(lengths),
            input_format=pb.InputFormat(layout=pb.KEYPOINT_LAYOUT_H36M_17, normalized=True),
            model=pb.MODEL_ONLINE_GRU,
        )
    )


def answer(frame: pb.Frame, frames_seen: int, index: int = -1) -> pb.StreamResponse:
    return pb.StreamResponse(
        frame=pb.AdjustedFrame(
            frame_index=frame.frame_index if index < 0 else index,
            adjusted_pose_3d=list(frame.pose_3d),
            bone_lengths=[0.1] * 16,
            frames_seen=frames_seen,
        )
    )


class Fake(pb_grpc.PoseAdjustmentServicer):
    def __init__(self, script: Script) -> None:
        self.script = script

    def Stream(self, request_iterator, context):
        yield from self.script(request_iterator, context)


@pytest.fixture
def fake() -> Iterator[Callable[[Script], str]]:
    servers = []

    def start(script: Script) -> str:
        server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
        pb_grpc.add_PoseAdjustmentServicer_to_server(Fake(script), server)
        port = server.add_insecure_port("127.0.0.1:0")
        server.start()
        servers.append(server)
        return f"http://127.0.0.1:{port}"

    yield start
    for s in servers:
        s.stop(0)


def session(url: str, **kw) -> blapose.Session:
    return blapose.Client(url, timeout=2).session(layout="h36m17", image_size=None, **kw)


@pytest.mark.parametrize("code", [3, 8, 13])
def test_in_band_codes(fake, code: int) -> None:
    def script(reqs, ctx):
        next(reqs)
        yield opened()
        for r in reqs:
            yield pb.StreamResponse(error=pb.FrameError(frame_index=r.frame.frame_index, code=code, message="no"))

    s = session(fake(script))
    with pytest.raises(blapose.FrameRejected) as e:
        s.send(KP, POSE)
    assert e.value.code.value[0] == code and e.value.message == "no"


def test_wrong_frame_index_is_protocol_error(fake) -> None:
    def script(reqs, ctx):
        next(reqs)
        yield opened()
        for r in reqs:
            yield answer(r.frame, 1, index=99)

    s = session(fake(script))
    with pytest.raises(blapose.ProtocolError):
        s.send(KP, POSE)
    with pytest.raises(blapose.BlaposeError):
        s.send(KP, POSE)


def test_wrong_frames_seen_is_protocol_error(fake) -> None:
    def script(reqs, ctx):
        next(reqs)
        yield opened()
        for r in reqs:
            yield answer(r.frame, 5)

    with pytest.raises(blapose.ProtocolError):
        session(fake(script)).send(KP, POSE)


def test_first_answer_not_opened_is_protocol_error(fake) -> None:
    def script(reqs, ctx):
        next(reqs)
        yield pb.StreamResponse(closed=pb.SessionClosed())

    with pytest.raises(blapose.ProtocolError):
        session(fake(script))


def test_stream_ending_with_frames_in_flight_is_protocol_error(fake) -> None:
    def script(reqs, ctx):
        next(reqs)
        yield opened()
        next(reqs)

    with pytest.raises(blapose.ProtocolError):
        session(fake(script)).send(KP, POSE)


def test_no_answer_to_open_is_deadline_exceeded(fake) -> None:
    release = threading.Event()

    def script(reqs, ctx):
        next(reqs)
        release.wait(10)
        return
        yield

    with pytest.raises(blapose.DeadlineExceeded):
        blapose.Client(fake(script), timeout=0.3).session(layout="h36m17")
    release.set()


def test_impossible_frames_seen_on_resume_is_protocol_error(fake) -> None:
    calls = []

    def script(reqs, ctx):
        first = next(reqs)
        calls.append(first.WhichOneof("kind"))
        if first.HasField("open"):
            yield opened()
            next(reqs)
            ctx.abort(grpc.StatusCode.UNAVAILABLE, "connection lost")  # looks like a dropped link
        else:
            yield opened(frames_seen=7, lengths=[0.1] * 16)  # more than was ever sent

    s = session(fake(script), resume_timeout=5)
    with pytest.raises(blapose.ProtocolError):
        s.send(KP, POSE)
    assert calls == ["open", "resume"]


def test_resume_rebuilds_a_lost_answer(fake) -> None:
    def script(reqs, ctx):
        first = next(reqs)
        if first.HasField("open"):
            yield opened()
            next(reqs)  # processed, but the answer is "lost"
            ctx.abort(grpc.StatusCode.UNAVAILABLE, "connection lost")
        else:
            yield opened(frames_seen=1, lengths=[0.2] * 16)
            for n, r in enumerate(reqs, start=2):
                yield answer(r.frame, n)

    s = session(fake(script), resume_timeout=5)
    r = s.send(KP, POSE)
    assert r.recovered and r.frames_seen == 1 and r.frame_index == 0
    np.testing.assert_allclose(r.bone_lengths, 0.2)
    np.testing.assert_allclose(r.adjusted, blapose.adjust_pose(POSE, [0.2] * 16))
    bones = np.linalg.norm(r.adjusted[1:] - r.adjusted[list(blapose.PARENTS[1:])], axis=1)
    np.testing.assert_allclose(bones, 0.2, rtol=1e-5)
    r2 = s.send(KP, POSE)
    assert not r2.recovered and r2.frames_seen == 2 and r2.frame_index == 1
    assert s.resumes == 1 and s.recovered == 1


def test_server_shutting_down_is_not_resumed(fake) -> None:
    def script(reqs, ctx):
        next(reqs)
        yield opened()
        next(reqs)
        ctx.abort(grpc.StatusCode.UNAVAILABLE, "the server is shutting down: ...")

    s = session(fake(script), resume_timeout=30)
    with pytest.raises(blapose.Unavailable, match="shutting down"):
        s.send(KP, POSE)
    assert s.resumes == 0
