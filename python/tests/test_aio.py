"""blapose.aio agrees with the sync client; its resumption and error paths."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import blapose
import blapose.aio
import numpy as np
import pytest
from conftest import EXAMPLES, Proxy, Server, free_port

TOL = 1e-5

# One event loop for every test of this module (as pytest-asyncio's
# module-scoped loop would give).
_LOOP = asyncio.new_event_loop()


def run_async(coro):
    return _LOOP.run_until_complete(coro)


def teardown_module() -> None:
    _LOOP.close()


def sync_results(server: Server, seq: blapose.ReplayFile):
    with blapose.Client(server.url) as client, client.session(layout=seq.layout, image_size=seq.image_size) as s:
        return list(s.stream(seq.frames()))


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.stem)
def test_async_equals_sync(server: Server, example: Path) -> None:
    seq = blapose.load_replay(example)
    ref = sync_results(server, seq)

    async def run():
        async with blapose.aio.Client(server.url) as client:
            info = await client.info()
            async with await client.session(layout=seq.layout, image_size=seq.image_size) as s:
                first = await s.send(seq.keypoints_2d[0], seq.pose_3d[0])
                rest = [r async for r in s.stream(list(seq.frames())[1:])]
                closed = await s.close()
            offline = await client.adjust_sequence(
                seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size
            )
            return info, [first] + rest, closed, offline

    info, results, closed, offline = run_async(run())
    assert info.protocol == "blapose.v1"
    assert closed.frames_seen == seq.num_frames
    assert [r.frame_index for r in results] == list(range(seq.num_frames))
    np.testing.assert_allclose(
        np.stack([r.adjusted for r in results]), np.stack([r.adjusted for r in ref]), atol=TOL, rtol=0
    )
    np.testing.assert_allclose(
        np.stack([r.bone_lengths for r in results]), np.stack([r.bone_lengths for r in ref]), atol=TOL, rtol=0
    )
    with blapose.Client(server.url) as client:
        sync_offline = client.adjust_sequence(
            seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size
        )
    np.testing.assert_allclose(offline.adjusted, sync_offline.adjusted, atol=TOL, rtol=0)


def test_async_stream_survives_a_cut_connection(server: Server, proxy: Proxy) -> None:
    seq = blapose.load_replay(EXAMPLES[0])
    ref = sync_results(server, seq)

    async def frames():
        for f in seq.frames():
            yield f

    async def run():
        results = []
        async with blapose.aio.Client(proxy.url) as client:
            async with await client.session(layout=seq.layout, image_size=seq.image_size) as s:
                async for r in s.stream(frames(), window=32):
                    results.append(r)
                    if len(results) == 20:
                        proxy.pause_downstream()
                        threading.Timer(0.5, proxy.cut).start()
                assert s.resumes == 1 and s.recovered > 0
                closed = await s.close()
        return results, closed

    results, closed = run_async(run())
    assert closed.frames_seen == seq.num_frames
    assert [r.frame_index for r in results] == list(range(seq.num_frames))
    assert [r.frames_seen for r in results] == list(range(1, seq.num_frames + 1))
    for r, e in zip(results, ref):
        if not r.recovered:
            np.testing.assert_allclose(r.adjusted, e.adjusted, atol=TOL, rtol=0)
    last = max(i for i, r in enumerate(results) if r.recovered)
    np.testing.assert_allclose(results[last].bone_lengths, ref[last].bone_lengths, atol=TOL, rtol=0)


def test_async_errors(server: Server, start_server) -> None:
    seq = blapose.load_replay(EXAMPLES[0])
    secured = start_server("--auth-token", "tok")

    async def run():
        async with blapose.aio.Client(server.url) as client:
            with pytest.raises(blapose.InvalidArgument):
                await client.session(layout="h36m17", image_size=(1000, 1000), model="bigru")
            with pytest.raises(blapose.NotFound):
                await client.resume("f" * 32)
            with pytest.raises(blapose.NotFound):
                await client.close_session("f" * 32)
            s = await client.session(layout=seq.layout, image_size=seq.image_size)
            await s.send(seq.keypoints_2d[0], seq.pose_3d[0])
            with pytest.raises(blapose.FrameRejected):
                await s.send(seq.keypoints_2d[1], np.zeros((17, 3)))
            frames = list(seq.frames())[:6]
            frames[2] = (frames[2][0], np.zeros((17, 3)))
            out = [r async for r in s.stream(frames, raise_on_error=False)]
            assert isinstance(out[2], blapose.FrameRejected)
            assert s.frames_seen == 6
            sid = await s.detach()
            r = await client.resume(sid)
            assert r.info.frames_seen == 6 and r.info.layout == seq.layout
            old_takeover = await client.resume(sid)  # takes the session over from r
            with pytest.raises(blapose.Aborted):
                await r.send(seq.keypoints_2d[0], seq.pose_3d[0])
            assert (await old_takeover.close()).frames_seen == 6
        async with blapose.aio.Client(secured.url) as client:
            with pytest.raises(blapose.Unauthenticated):
                await client.info()
        async with blapose.aio.Client(secured.url, token="tok") as client:
            assert (await client.info()).protocol == "blapose.v1"
        async with blapose.aio.Client(f"http://127.0.0.1:{free_port()}", timeout=5) as client:
            with pytest.raises(blapose.Unavailable):
                await client.info()
            with pytest.raises(blapose.Unavailable):
                await client.session(layout=seq.layout, image_size=seq.image_size)

    run_async(run())
