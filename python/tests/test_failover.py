"""Failover across replicas with session tokens, and the affinity header.

Real server binaries sharing a ``--session-key``: a session streaming a shipped
example moves to another replica when its server dies (SIGKILL) or shuts down
(SIGTERM), restored from its latest token; its answers equal an uninterrupted
run's. Plus: tokens under another key are refused, and every call of a session
carries one ``blapose-affinity`` key (checked on an in-process gRPC server).
"""

from __future__ import annotations

import asyncio
import re
import signal
import threading
from concurrent import futures
from typing import Dict, Iterator, List, Tuple

import grpc
import numpy as np
import pytest
from conftest import REPO, Proxy, Server, free_port

import blapose
from blapose.v1 import blapose_pb2 as pb
from blapose.v1 import blapose_pb2_grpc as pb_grpc

KEY = "a shared key of more than 16 bytes"
OTHER_KEY = "another key, also more than 16 bytes"
EVERY = 10
TOL = 1e-6
EXAMPLE = REPO / "examples" / "cmu_02_02_walk.npz"


def keyed(start_server, key: str = KEY) -> Server:
    return start_server("--session-key", key, "--token-every", str(EVERY))


@pytest.fixture(scope="module")
def seq() -> blapose.ReplayFile:
    return blapose.load_replay(EXAMPLE)


@pytest.fixture(scope="module")
def reference(server: Server, seq: blapose.ReplayFile):
    """An uninterrupted run (the shared server has no key; same weights, same answers)."""
    with blapose.Client(server.url) as client, client.session(layout=seq.layout, image_size=seq.image_size) as s:
        results = list(s.stream(seq.frames()))
        closed = s.close()
    return results, closed


def check_exact(results, closed, reference, seq) -> None:
    """Every frame answered exactly once, in order, as by an uninterrupted session."""
    ref, ref_closed = reference
    n = seq.num_frames
    assert [r.frame_index for r in results] == list(range(n))
    assert [r.frames_seen for r in results] == list(range(1, n + 1))
    assert not any(r.recovered for r in results), "every answer is the server's own"
    for r, e in zip(results, ref):
        np.testing.assert_allclose(r.bone_lengths, e.bone_lengths, rtol=0, atol=TOL)
        np.testing.assert_allclose(r.adjusted, e.adjusted, rtol=0, atol=TOL)
    assert closed.frames_seen == n, "no frame processed twice or skipped"
    np.testing.assert_allclose(closed.bone_lengths, ref_closed.bone_lengths, rtol=0, atol=TOL)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["killed", "shut-down"])
def test_session_moves_to_another_replica(start_server, seq, reference, sig) -> None:
    a, b = keyed(start_server), keyed(start_server)
    results = []
    with blapose.Client([a.url, b.url], timeout=10) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size, resume_timeout=20) as s:
            assert s.url == a.url
            assert s.token is not None and s.token.frames_seen == 0 and s.token.session_id == s.session_id
            for r in s.stream(seq.frames(), window=16):
                results.append(r)
                if len(results) == 35:
                    assert s.token is not None and s.token.frames_seen == 30  # every 10 frames
                    if sig == signal.SIGKILL:
                        a.proc.kill()  # frames and answers in flight are lost
                    else:
                        a.proc.send_signal(sig)  # drains: answers, a last token, UNAVAILABLE
            assert s.url == b.url, "the session moved to B"
            assert s.resumes >= 1 and s.recovered == 0
            assert s.token is not None and s.token.frames_seen <= s.frames_seen == seq.num_frames
            closed = s.close()
    a.proc.wait(timeout=15)
    check_exact(results, closed, reference, seq)


def test_answers_lost_in_flight_are_recovered_from_the_token(start_server, seq, reference) -> None:
    """Same replica, the connection drops with answers withheld: the held session is ahead of
    the answers received, so it is closed there and restored from the token (nothing rebuilt)."""
    srv = keyed(start_server)
    proxy = Proxy(srv.port)
    results = []
    try:
        with blapose.Client(proxy.url) as client:
            with client.session(layout=seq.layout, image_size=seq.image_size, resume_timeout=20) as s:
                for r in s.stream(seq.frames(), window=32):
                    results.append(r)
                    if len(results) == 25:
                        proxy.pause_downstream()
                        threading.Timer(0.5, proxy.cut).start()
                assert s.resumes >= 1 and s.recovered == 0
                closed = s.close()
    finally:
        proxy.close()
    check_exact(results, closed, reference, seq)


def test_send_resumes_on_the_next_server_and_skips_a_dead_one(start_server, seq, reference) -> None:
    a, b = keyed(start_server), keyed(start_server)
    dead = f"http://127.0.0.1:{free_port()}"
    results = []
    with blapose.Client([dead, a.url, b.url], timeout=10) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size) as s:
            assert s.url == a.url  # the dead one was skipped
            for i, (k, p) in enumerate(seq.frames()):
                if i == 17:
                    a.proc.kill()
                results.append(s.send(k, p))
            assert s.url == b.url and s.resumes == 1
            closed = s.close()
    check_exact(results, closed, reference, seq)


def test_request_token_and_resume_elsewhere(start_server, seq) -> None:
    a, b = keyed(start_server), keyed(start_server)
    with blapose.Client(a.url) as ca, blapose.Client(b.url) as cb:
        s = ca.session(layout=seq.layout, image_size=seq.image_size)
        first = list(s.stream(zip(seq.keypoints_2d[:13], seq.pose_3d[:13])))
        assert s.token is not None and s.token.frames_seen == 10
        token = s.request_token()
        assert token.frames_seen == 13 and s.token == token and len(token.token) > 1000
        affinity, sid = s.affinity, s.detach()
        with cb.resume(sid, token=token, affinity=affinity) as r:
            assert r.info.resumed and r.info.frames_seen == 13 and r.affinity == affinity
            nxt = r.send(seq.keypoints_2d[13], seq.pose_3d[13])
            assert nxt.frame_index == 13 and nxt.frames_seen == 14
        # Closing a session ends its tokens where it lived: B, which closed it, refuses the token.
        with pytest.raises(blapose.FailedPrecondition, match="closed"):
            cb.resume(sid, token=token)
        # Raw bytes work too: A still holds the detached session, and a resume with a token
        # continues from the token's state (frame 13).
        with ca.resume(sid, token=token.token, affinity=affinity) as r2:
            assert r2.info.frames_seen == 13
    assert [r.frames_seen for r in first] == list(range(1, 14))


def test_a_token_under_another_key_is_refused(start_server, seq) -> None:
    a, other, plain = keyed(start_server), keyed(start_server, OTHER_KEY), start_server()
    with blapose.Client(a.url) as ca:
        s = ca.session(layout=seq.layout, image_size=seq.image_size)
        s.send(seq.keypoints_2d[0], seq.pose_3d[0])
        token = s.request_token()
        sid = s.detach()
    with blapose.Client(other.url) as co, pytest.raises(blapose.Unauthenticated, match="another session key"):
        co.resume(sid, token=token)
    with blapose.Client(plain.url) as cp:
        with pytest.raises(blapose.FailedPrecondition):
            cp.resume(sid, token=token)
        # A server without a key issues no tokens.
        with cp.session(layout=seq.layout, image_size=seq.image_size) as s2:
            assert s2.token is None
            with pytest.raises(blapose.FailedPrecondition, match="no session token"):
                s2.request_token()
            assert s2.send(seq.keypoints_2d[0], seq.pose_3d[0]).frames_seen == 1  # still usable


def test_failover_gives_up_with_a_refusal(start_server, seq) -> None:
    """The only other replica has another key: the session ends with UNAUTHENTICATED."""
    a, other = keyed(start_server), keyed(start_server, OTHER_KEY)
    with blapose.Client([a.url, other.url], timeout=5) as client:
        s = client.session(layout=seq.layout, image_size=seq.image_size, resume_timeout=5)
        s.send(seq.keypoints_2d[0], seq.pose_3d[0])
        a.proc.kill()
        with pytest.raises(blapose.Unauthenticated):
            s.send(seq.keypoints_2d[1], seq.pose_3d[1])


def test_aio_session_moves(start_server, seq, reference) -> None:
    a, b = keyed(start_server), keyed(start_server)

    async def run():
        results = []
        async with blapose.aio.Client([a.url, b.url], timeout=10) as client:
            async with await client.session(layout=seq.layout, image_size=seq.image_size) as s:
                async for r in s.stream(seq.frames(), window=8):
                    results.append(r)
                    if len(results) == 42:
                        a.proc.kill()
                assert s.url == b.url and s.resumes >= 1
                assert (await s.request_token()).frames_seen == seq.num_frames
                assert s.token is not None and re.fullmatch("[0-9a-f]{32}", s.affinity)
                closed = await s.close()
        return results, closed

    results, closed = asyncio.run(run())
    check_exact(results, closed, reference, seq)


# -- the affinity header, on an in-process server --------------------------------


class Recorder(grpc.ServerInterceptor):
    def __init__(self) -> None:
        self.calls: List[Tuple[str, Dict[str, str]]] = []

    def intercept_service(self, continuation, details):
        self.calls.append((details.method.rsplit("/", 1)[-1], dict(details.invocation_metadata)))
        return continuation(details)


class Fake(pb_grpc.PoseAdjustmentServicer):
    """Open/resume, answer frames; the first stream drops after its first frame."""

    def __init__(self) -> None:
        self.streams = 0

    def Stream(self, request_iterator: Iterator[pb.StreamRequest], context):
        self.streams += 1
        first = next(request_iterator)
        seen = 0 if first.HasField("open") else 1
        yield pb.StreamResponse(
            opened=pb.SessionOpened(
                session_id=first.resume.session_id or "b" * 32,
                resumed=first.HasField("resume"),
                frames_seen=seen,
                bone_lengths=[0.1] * 16 if seen else [],
                input_format=pb.InputFormat(layout=pb.KEYPOINT_LAYOUT_H36M_17, normalized=True),
                model=pb.MODEL_ONLINE_GRU,
                session_token=b"token-bytes",
            )
        )
        for req in request_iterator:
            if req.HasField("close"):
                yield pb.StreamResponse(closed=pb.SessionClosed(session_id="b" * 32, frames_seen=seen))
                return
            seen += 1
            yield pb.StreamResponse(
                frame=pb.AdjustedFrame(
                    frame_index=req.frame.frame_index,
                    adjusted_pose_3d=list(req.frame.pose_3d),
                    bone_lengths=[0.1] * 16,
                    frames_seen=seen,
                )
            )
            if self.streams == 1:
                context.abort(grpc.StatusCode.UNAVAILABLE, "connection lost")

    def CloseSession(self, request, context):
        return pb.CloseSessionResponse(frames_seen=2)

    def ModelInfo(self, request, context):
        return pb.ModelInfoResponse(server_version="fake")


def test_every_call_of_a_session_carries_its_affinity_key() -> None:
    recorder = Recorder()
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=4), interceptors=[recorder])
    pb_grpc.add_PoseAdjustmentServicer_to_server(Fake(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        kp, pose = np.zeros((17, 2)), np.arange(51, dtype=np.float32).reshape(17, 3) * 0.01
        with blapose.Client(f"http://127.0.0.1:{port}", token="secret", timeout=5) as client:
            client.info()
            s = client.session(layout="h36m17", resume_timeout=5)
            s.send(kp, pose)  # answered, then the stream drops: a resume follows
            assert s.send(kp, pose).frames_seen == 2
            assert s.resumes == 1
            s.detach()
            client.close_session(s.session_id, affinity=s.affinity)
            other = client.session(layout="h36m17")
            other.detach()
    finally:
        server.stop(0)
    key = s.affinity
    assert re.fullmatch("[0-9a-f]{32}", key)
    assert other.affinity != key
    methods = [m for m, _ in recorder.calls]
    assert methods == ["ModelInfo", "Stream", "Stream", "CloseSession", "Stream"]
    assert all(md.get("authorization") == "Bearer secret" for _, md in recorder.calls)
    assert "blapose-affinity" not in recorder.calls[0][1]  # not tied to a session
    assert [md.get("blapose-affinity") for _, md in recorder.calls[1:4]] == [key] * 3
    assert recorder.calls[4][1].get("blapose-affinity") == other.affinity


def test_gives_up_after_max_resumes_in_a_row() -> None:
    """A server that drops every stream at its first frame: resumed max_resumes times, then the error."""
    opens: List[str] = []

    class Dropping(pb_grpc.PoseAdjustmentServicer):
        def Stream(self, request_iterator, context):
            first = next(request_iterator)
            opens.append(first.WhichOneof("kind"))
            yield pb.StreamResponse(
                opened=pb.SessionOpened(
                    session_id="c" * 32,
                    input_format=pb.InputFormat(layout=pb.KEYPOINT_LAYOUT_H36M_17, normalized=True),
                    model=pb.MODEL_ONLINE_GRU,
                    session_token=b"token-bytes",
                )
            )
            next(request_iterator)
            context.abort(grpc.StatusCode.UNAVAILABLE, "connection lost")

    server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    pb_grpc.add_PoseAdjustmentServicer_to_server(Dropping(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        with blapose.Client(f"http://127.0.0.1:{port}", timeout=5) as client:
            s = client.session(layout="h36m17", max_resumes=3, resume_timeout=5)
            with pytest.raises(blapose.Unavailable, match="connection lost"):
                s.send(np.zeros((17, 2)), np.arange(51, dtype=np.float32).reshape(17, 3) * 0.01)
            assert s.resumes == 3
    finally:
        server.stop(0)
    assert opens == ["open", "resume", "resume", "resume"]


def test_asks_for_a_fresh_token_when_the_server_sends_none_unasked(start_server, seq, monkeypatch) -> None:
    """--token-every 0: the session asks for a token now and then, so it keeps few frames to resend."""
    monkeypatch.setattr(blapose._common, "TOKEN_REFRESH", 20)
    srv = start_server("--session-key", KEY, "--token-every", "0")
    with blapose.Client(srv.url) as client, client.session(layout=seq.layout, image_size=seq.image_size) as s:
        results = list(s.stream(seq.frames(), window=8))
        assert [r.frames_seen for r in results] == list(range(1, seq.num_frames + 1))
        assert s.token is not None and seq.num_frames - 20 - 8 <= s.token.frames_seen <= seq.num_frames
        assert len(s._core.history) == seq.num_frames - s.token.frames_seen
