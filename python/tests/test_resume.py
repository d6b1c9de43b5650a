"""Resumption after the connection is cut mid-stream (a TCP proxy in front of the real server)."""

from __future__ import annotations

import threading

import blapose
import numpy as np
import pytest
from conftest import EXAMPLES, Proxy, Server

TOL = 1e-5


def reference(server: Server, seq: blapose.ReplayFile):
    with blapose.Client(server.url) as client, client.session(layout=seq.layout, image_size=seq.image_size) as s:
        return list(s.stream(seq.frames()))


def check_complete(results, ref, seq) -> None:
    """One result per frame, in order, and every frame counted exactly once."""
    assert [r.frame_index for r in results] == list(range(seq.num_frames))
    assert [r.frames_seen for r in results] == list(range(1, seq.num_frames + 1))
    for r, e in zip(results, ref):
        if not r.recovered:
            # Same session state as an uninterrupted stream: same answers.
            np.testing.assert_allclose(r.adjusted, e.adjusted, rtol=0, atol=TOL)
            np.testing.assert_allclose(r.bone_lengths, e.bone_lengths, rtol=0, atol=TOL)
    recovered = [i for i, r in enumerate(results) if r.recovered]
    if recovered:
        # The resumed estimate is the one after the last lost frame.
        last = recovered[-1]
        np.testing.assert_allclose(results[last].bone_lengths, ref[last].bone_lengths, rtol=0, atol=TOL)
        np.testing.assert_allclose(results[last].adjusted, ref[last].adjusted, rtol=0, atol=1e-4)
        assert recovered == list(range(recovered[0], last + 1))  # one contiguous run


@pytest.mark.parametrize("pause", [True, False], ids=["answers-withheld", "plain-cut"])
def test_stream_survives_a_cut_connection(server: Server, proxy: Proxy, pause: bool) -> None:
    seq = blapose.load_replay(EXAMPLES[0])
    ref = reference(server, seq)
    results = []
    with blapose.Client(proxy.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size, resume_timeout=20) as s:
            for r in s.stream(seq.frames(), window=32):
                results.append(r)
                if len(results) == 20:
                    if pause:
                        # Answers stop reaching us while the server keeps processing
                        # the frames in flight; then the link dies.
                        proxy.pause_downstream()
                        threading.Timer(0.5, proxy.cut).start()
                    else:
                        proxy.cut()
            assert s.resumes == 1
            if pause:
                assert s.recovered > 0, "the withheld answers should have been rebuilt"
            assert s.recovered == sum(r.recovered for r in results)
            closed = s.close()
    assert proxy.accepted == 2
    assert closed.frames_seen == seq.num_frames  # nothing lost, nothing counted twice
    check_complete(results, ref, seq)
    np.testing.assert_allclose(closed.bone_lengths, ref[-1].bone_lengths, rtol=0, atol=TOL)


def test_send_survives_a_cut_connection(server: Server, proxy: Proxy) -> None:
    seq = blapose.load_replay(EXAMPLES[1])
    ref = reference(server, seq)
    results = []
    with blapose.Client(proxy.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size) as s:
            for i, (k, p) in enumerate(seq.frames()):
                if i in (10, 40):
                    proxy.cut()
                results.append(s.send(k, p))
            assert s.resumes == 2
            assert s.recovered == 0  # nothing was in flight at the cuts
            closed = s.close()
    assert closed.frames_seen == seq.num_frames
    check_complete(results, ref, seq)


def test_no_auto_resume_raises_unavailable(server: Server, proxy: Proxy) -> None:
    seq = blapose.load_replay(EXAMPLES[0])
    with blapose.Client(proxy.url) as client:
        s = client.session(layout=seq.layout, image_size=seq.image_size, auto_resume=False)
        s.send(seq.keypoints_2d[0], seq.pose_3d[0])
        proxy.cut()
        with pytest.raises(blapose.Unavailable):
            s.send(seq.keypoints_2d[1], seq.pose_3d[1])
        # The session outlived its connection: resume it by id, continue from frames_seen.
        r = client.resume(s.session_id)
        assert r.info.resumed and r.info.frames_seen == 1
        assert r.info.layout == seq.layout and r.info.image_size == seq.image_size
        res = r.send(seq.keypoints_2d[1], seq.pose_3d[1])
        assert res.frame_index == 1 and res.frames_seen == 2
        assert r.close().frames_seen == 2


def test_detach_and_resume_by_id(server: Server) -> None:
    seq = blapose.load_replay(EXAMPLES[2])
    ref = reference(server, seq)
    half = seq.num_frames // 2
    with blapose.Client(server.url) as client:
        s = client.session(layout=seq.layout, image_size=seq.image_size)
        first = list(s.stream(zip(seq.keypoints_2d[:half], seq.pose_3d[:half])))
        sid = s.detach()
        with client.resume(sid) as r:
            assert r.info.frames_seen == half
            np.testing.assert_allclose(r.info.bone_lengths, ref[half - 1].bone_lengths, rtol=0, atol=TOL)
            rest = list(r.stream(zip(seq.keypoints_2d[half:], seq.pose_3d[half:])))
    check_complete(first + rest, ref, seq)
    with blapose.Client(server.url) as client, pytest.raises(blapose.NotFound):
        client.resume(sid)  # closed on leaving the with block
