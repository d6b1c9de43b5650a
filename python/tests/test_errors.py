"""Every error path: typed exceptions for gRPC statuses, in-band frame errors, local checks."""

from __future__ import annotations

import dataclasses
import signal
import time

import blapose
import grpc
import numpy as np
import pytest
from blapose.errors import from_grpc_error, status_code
from conftest import EXAMPLES, Server, free_port


@pytest.fixture(scope="module")
def seq() -> blapose.ReplayFile:
    return blapose.load_replay(EXAMPLES[0])


def open_session(client: blapose.Client, seq: blapose.ReplayFile, **kw) -> blapose.Session:
    return client.session(layout=seq.layout, image_size=seq.image_size, **kw)


# -- stream-ending statuses on open ------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [
        {"layout": 0, "image_size": (1000, 1000)},  # KEYPOINT_LAYOUT_UNSPECIFIED
        {"layout": "h36m17", "image_size": (0, 1000)},  # zero image size
        {"layout": "h36m17", "image_size": (1000, 1000), "model": "bigru"},  # Bi-GRU on a stream
        {
            "layout": "h36m17",
            "image_size": (1000, 1000),
            "camera": blapose.Camera(up=(0, -1, 0), focal=(-5, 5), principal=(500, 500)),
        },  # focal length <= 0
    ],
    ids=["layout-unset", "zero-image", "bigru-stream", "bad-camera"],
)
def test_bad_open_is_invalid_argument(server: Server, kwargs) -> None:
    with blapose.Client(server.url) as client, pytest.raises(blapose.InvalidArgument) as e:
        client.session(**kwargs)
    assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details


def test_server_lifter_on_a_server_without_one_is_invalid_argument(start_server) -> None:
    srv = start_server("--no-lifter")
    with blapose.Client(srv.url) as client:
        with pytest.raises(blapose.InvalidArgument) as e:
            client.session(layout="h36m17", image_size=(1000, 1000), server_lifter=True)
        assert "--no-lifter" in e.value.details
        assert client.info().lifter is None


def test_the_default_server_lifts(server: Server) -> None:
    with blapose.Client(server.url) as client:
        lifter = client.info().lifter
        assert lifter is not None and lifter["causal"], lifter
        with client.session(layout="h36m17", image_size=(1000, 1000), server_lifter=True) as s:
            assert s.info.lifter == lifter["name"]


def test_a_bad_lens_distortion_is_named(server: Server, seq) -> None:
    assert seq.camera is not None
    good = dataclasses.replace(seq.camera, distortion=(-0.2, 0.05, 0.001, -0.001))
    back = blapose.Camera.from_proto(good.to_proto())
    assert back.distortion is not None and np.allclose(back.distortion, good.distortion)
    with blapose.Client(server.url) as client:
        s = open_session(client, seq, camera=good)
        assert s.send(seq.keypoints_2d[0], seq.pose_3d[0]).frames_seen == 1
        s.close()
        bad = dataclasses.replace(seq.camera, distortion=(0.1, 0.2, 0.3))
        with pytest.raises(blapose.InvalidArgument) as e:
            open_session(client, seq, camera=bad)
    assert "camera.distortion" in e.value.details


def test_unknown_session_is_not_found(server: Server) -> None:
    with blapose.Client(server.url) as client:
        with pytest.raises(blapose.NotFound):
            client.resume("0" * 32)
        with pytest.raises(blapose.NotFound):
            client.close_session("0" * 32)


def test_close_session_by_id(server: Server, seq) -> None:
    with blapose.Client(server.url) as client:
        s = open_session(client, seq)
        s.send(seq.keypoints_2d[0], seq.pose_3d[0])
        sid = s.detach()
        closed = client.close_session(sid)
        assert closed.frames_seen == 1 and closed.bone_lengths.shape == (16,)
        with pytest.raises(blapose.NotFound):
            client.resume(sid)


def test_takeover_aborts_the_old_stream(server: Server, seq) -> None:
    with blapose.Client(server.url) as client:
        old = open_session(client, seq)
        old.send(seq.keypoints_2d[0], seq.pose_3d[0])
        new = client.resume(old.session_id)
        with pytest.raises(blapose.Aborted):
            old.send(seq.keypoints_2d[1], seq.pose_3d[1])
        with pytest.raises(blapose.BlaposeError):
            old.send(seq.keypoints_2d[1], seq.pose_3d[1])  # the failed session stays failed
        assert new.send(seq.keypoints_2d[1], seq.pose_3d[1]).frames_seen == 2
        new.close()


def test_too_many_sessions_is_resource_exhausted(start_server, seq) -> None:
    srv = start_server("--max-sessions", "1")
    with blapose.Client(srv.url) as client:
        with open_session(client, seq):
            with pytest.raises(blapose.ResourceExhausted):
                open_session(client, seq)
        with open_session(client, seq) as s:  # freed by the close
            s.send(seq.keypoints_2d[0], seq.pose_3d[0])


def test_message_over_the_limit_is_out_of_range(start_server, seq) -> None:
    srv = start_server("--max-message-bytes", "4096")
    with blapose.Client(srv.url) as client, pytest.raises(blapose.OutOfRange):
        client.adjust_sequence(seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size)


def test_token(start_server, seq) -> None:
    srv = start_server("--auth-token", "s3cret")
    with blapose.Client(srv.url) as client:
        with pytest.raises(blapose.Unauthenticated):
            client.info()
        with pytest.raises(blapose.Unauthenticated):
            open_session(client, seq)
    with blapose.Client(srv.url, token="wrong") as client, pytest.raises(blapose.Unauthenticated):
        client.info()
    with blapose.Client(srv.url, token="s3cret") as client:
        assert client.info().protocol == "blapose.v1"
        with open_session(client, seq) as s:
            assert s.send(seq.keypoints_2d[0], seq.pose_3d[0]).frames_seen == 1


def test_no_server_is_unavailable(seq) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    with blapose.Client(url, timeout=5) as client:
        with pytest.raises(blapose.Unavailable):
            client.info()
        with pytest.raises(blapose.Unavailable):
            open_session(client, seq)
        with pytest.raises(blapose.Unavailable):
            client.wait_ready(timeout=0.2)


def test_client_deadline_is_deadline_exceeded(server: Server, seq) -> None:
    kp = np.repeat(seq.keypoints_2d, 40, axis=0)
    poses = np.repeat(seq.pose_3d, 40, axis=0)
    with blapose.Client(server.url, timeout=0.001) as client, pytest.raises(blapose.DeadlineExceeded):
        client.adjust_sequence(kp, poses, layout=seq.layout, image_size=seq.image_size)


def test_bad_adjust_sequence_is_invalid_argument(server: Server, seq) -> None:
    poses = seq.pose_3d.copy()
    poses[3] = 0.0  # zero-length bones in frame 3
    with blapose.Client(server.url) as client, pytest.raises(blapose.InvalidArgument) as e:
        client.adjust_sequence(seq.keypoints_2d, poses, layout=seq.layout, image_size=seq.image_size)
    assert "3" in e.value.details


def test_server_shutdown_is_unavailable_and_not_resumed(start_server, seq) -> None:
    srv = start_server()
    with blapose.Client(srv.url) as client:
        s = open_session(client, seq, resume_timeout=2)
        s.send(seq.keypoints_2d[0], seq.pose_3d[0])
        srv.stop(signal.SIGTERM)
        t = time.monotonic()
        with pytest.raises(blapose.Unavailable):
            s.send(seq.keypoints_2d[1], seq.pose_3d[1])
        assert time.monotonic() - t < 10


# -- in-band frame errors -------------------------------------------------------------


def test_frame_rejected_leaves_the_session_unchanged(server: Server, seq) -> None:
    with blapose.Client(server.url) as client, open_session(client, seq) as s:
        s.send(seq.keypoints_2d[0], seq.pose_3d[0])
        with pytest.raises(blapose.FrameRejected) as e:
            s.send(seq.keypoints_2d[1], np.zeros((17, 3)))  # zero-length bones
        assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT and e.value.frame_index == 1
        with pytest.raises(blapose.FrameRejected):
            s.send(seq.keypoints_2d[1] + 2e6, seq.pose_3d[1])  # beyond +-1e6
        r = s.send(seq.keypoints_2d[1], seq.pose_3d[1], frame_index=1)
        assert r.frames_seen == 2 and s.frames_seen == 2


def test_stream_frame_errors(server: Server, seq) -> None:
    frames = list(seq.frames())[:10]
    frames[4] = (frames[4][0], np.zeros((17, 3)))
    with blapose.Client(server.url) as client, open_session(client, seq) as s:
        out = list(s.stream(frames, raise_on_error=False))
        assert [type(r).__name__ for r in out].count("FrameRejected") == 1
        assert isinstance(out[4], blapose.FrameRejected) and out[4].frame_index == 4
        assert [r.frames_seen for r in out if isinstance(r, blapose.FrameResult)] == list(range(1, 10))
        with pytest.raises(blapose.FrameRejected):
            list(s.stream(frames))
        # After the raise the in-flight answers were drained: the session goes on.
        assert s.frames_seen == 9 + 9
        assert s.send(*frames[0]).frames_seen == 19


def test_stream_stopped_early_keeps_the_session_usable(server: Server, seq) -> None:
    with blapose.Client(server.url) as client, open_session(client, seq) as s:
        for i, _ in enumerate(s.stream(seq.frames(), window=16)):
            if i == 3:
                break
        assert s.frames_seen >= 4
        n = s.frames_seen
        assert s.send(seq.keypoints_2d[0], seq.pose_3d[0]).frames_seen == n + 1


# -- local checks (nothing sent) -----------------------------------------------------


def test_local_input_errors(server: Server, seq) -> None:
    with blapose.Client(server.url) as client:
        with pytest.raises(ValueError):
            client.session(layout="openpose25", image_size=(10, 10))
        with pytest.raises(ValueError):
            client.session(layout="coco17", image_size=(10, 10), model="lstm")
        with open_session(client, seq) as s:
            with pytest.raises(ValueError):
                s.send(np.zeros((16, 2)), seq.pose_3d[0])  # h36m17 needs 17 joints
            with pytest.raises(ValueError):
                s.send(seq.keypoints_2d[0], np.full((17, 3), np.nan))
            with pytest.raises(ValueError):
                s.send(seq.keypoints_2d[0])  # no pose and no server lifter
            assert s.send(seq.keypoints_2d[0], seq.pose_3d[0]).frames_seen == 1
        with pytest.raises(ValueError):
            client.adjust_sequence(seq.keypoints_2d, seq.pose_3d[:-1], layout=seq.layout, image_size=seq.image_size)
    with pytest.raises(ValueError):
        blapose.Client("ftp://x:1")


def test_status_code_mapping() -> None:
    class Fake(grpc.RpcError):
        def __init__(self, code):
            self._code = code

        def code(self):
            return self._code

        def details(self):
            return "d"

    for code in grpc.StatusCode:
        if code == grpc.StatusCode.OK:
            continue
        err = from_grpc_error(Fake(code))
        assert isinstance(err, blapose.RpcError) and err.code == code
        assert status_code(code.value[0]) == code
    assert isinstance(from_grpc_error(Fake(grpc.StatusCode.NOT_FOUND)), blapose.NotFound)


class _FakeRpcError(grpc.RpcError):
    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        self._code, self._details = code, details

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details


def test_a_deadline_the_server_noticed_first_is_deadline_exceeded() -> None:
    from blapose.errors import from_grpc_error

    raced = from_grpc_error(_FakeRpcError(grpc.StatusCode.CANCELLED, "Timeout%20expired"))
    assert isinstance(raced, blapose.DeadlineExceeded)
    other = from_grpc_error(_FakeRpcError(grpc.StatusCode.CANCELLED, "client went away"))
    assert isinstance(other, blapose.Cancelled)
