"""Python results equal `blapose-client replay` / `adjust` on every shipped example."""

from __future__ import annotations

import subprocess
from pathlib import Path

import blapose
import numpy as np
import pytest
from conftest import CLIENT_BIN, EXAMPLES, Server

TOL = 1e-5  # metres


def cli(server: Server, *args: str) -> None:
    if not CLIENT_BIN.exists():
        pytest.fail(f"{CLIENT_BIN} is missing: cargo build --release -p blapose-server -p blapose-client")
    subprocess.run([str(CLIENT_BIN), "--server", server.url, *args], check=True, capture_output=True, timeout=120)


def cli_reference(server: Server, example: Path, tmp_path: Path, *args: str):
    """The CLI's output for ``example`` (``args``: the subcommand and its flags), and the replay itself."""
    out = tmp_path / "cli.npz"
    cli(server, args[0], str(example), *args[1:], "--out", str(out))
    return np.load(out), blapose.load_replay(example)


def test_examples_exist() -> None:
    assert len(EXAMPLES) >= 5


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.stem)
def test_stream_equals_cli_replay(server: Server, example: Path, tmp_path: Path) -> None:
    ref, seq = cli_reference(server, example, tmp_path, "replay")
    with blapose.Client(server.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size) as s:
            results = list(s.stream(seq.frames()))
            closed = s.close()
    assert [r.frame_index for r in results] == list(range(seq.num_frames))
    assert [r.frames_seen for r in results] == list(range(1, seq.num_frames + 1))
    assert closed.frames_seen == seq.num_frames
    adjusted = np.stack([r.adjusted for r in results])
    lengths = np.stack([r.bone_lengths for r in results])
    assert adjusted.shape == ref["adjusted_3d"].shape == (seq.num_frames, 17, 3)
    assert lengths.shape == ref["bone_lengths"].shape == (seq.num_frames, 16)
    np.testing.assert_allclose(adjusted, ref["adjusted_3d"], rtol=0, atol=TOL)
    np.testing.assert_allclose(lengths, ref["bone_lengths"], rtol=0, atol=TOL)
    np.testing.assert_allclose(closed.bone_lengths, lengths[-1], rtol=0, atol=0)


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.stem)
def test_adjust_sequence_equals_cli_adjust(server: Server, example: Path, tmp_path: Path) -> None:
    ref, seq = cli_reference(server, example, tmp_path, "adjust")
    with blapose.Client(server.url) as client:
        res = client.adjust_sequence(seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size)
    assert res.model == "bigru"
    np.testing.assert_allclose(res.adjusted, ref["adjusted_3d"], rtol=0, atol=TOL)
    np.testing.assert_allclose(res.bone_lengths, ref["bone_lengths"], rtol=0, atol=TOL)


def test_camera_session_equals_cli_replay_camera(server: Server, tmp_path: Path) -> None:
    ref, seq = cli_reference(server, EXAMPLES[0], tmp_path, "replay", "--camera")
    assert seq.camera is not None
    with blapose.Client(server.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size, camera=seq.camera) as s:
            assert s.info.camera is not None
            results = list(s.stream(seq.frames(), window=16))
    np.testing.assert_allclose(np.stack([r.adjusted for r in results]), ref["adjusted_3d"], rtol=0, atol=TOL)
    np.testing.assert_allclose(np.stack([r.bone_lengths for r in results]), ref["bone_lengths"], rtol=0, atol=TOL)


def test_send_equals_stream_and_online_adjust_sequence(server: Server) -> None:
    seq = blapose.load_replay(EXAMPLES[0])
    n = 30
    with blapose.Client(server.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size) as s:
            one_by_one = [s.send(k, p) for k, p in zip(seq.keypoints_2d[:n], seq.pose_3d[:n])]
        with client.session(layout=seq.layout, image_size=seq.image_size) as s:
            streamed = list(s.stream(zip(seq.keypoints_2d[:n], seq.pose_3d[:n]), window=1))
        offline = client.adjust_sequence(
            seq.keypoints_2d[:n], seq.pose_3d[:n], layout=seq.layout, image_size=seq.image_size, model="gru"
        )
    assert offline.model == "gru"
    for a, b in zip(one_by_one, streamed):
        assert a.frame_index == b.frame_index
        np.testing.assert_allclose(a.adjusted, b.adjusted, rtol=0, atol=TOL)
    np.testing.assert_allclose(np.stack([r.bone_lengths for r in streamed]), offline.bone_lengths, rtol=0, atol=TOL)


def test_info(server: Server) -> None:
    with blapose.Client(server.url) as client:
        info = client.info()
    assert info.protocol == "blapose.v1"
    assert info.joint_names == blapose.JOINT_NAMES
    assert info.bone_names == blapose.BONE_NAMES
    assert set(info.layouts) == {"h36m17", "sh16", "coco17"}
    assert {m["model"] for m in info.models} == {"gru", "bigru"}


def test_local_adjust_pose_matches_server(server: Server) -> None:
    seq = blapose.load_replay(EXAMPLES[1])
    with blapose.Client(server.url) as client, client.session(layout=seq.layout, image_size=seq.image_size) as s:
        results = list(s.stream(seq.frames()))
    for r, pose in zip(results[::10], seq.pose_3d[::10]):
        np.testing.assert_allclose(blapose.adjust_pose(pose, r.bone_lengths), r.adjusted, rtol=0, atol=TOL)


def test_motion_adjust_sequence_equals_cli_adjust_motion(server: Server, tmp_path: Path) -> None:
    example = next(p for p in EXAMPLES if "walk" in p.stem)
    ref, seq = cli_reference(server, example, tmp_path, "adjust", "--camera", "--motion")
    assert seq.camera is not None
    with blapose.Client(server.url) as client:
        plain = client.adjust_sequence(seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size)
        res = client.adjust_sequence(
            seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size, camera=seq.camera, motion=50
        )
    assert plain.root_positions is None and res.root_positions is not None
    assert res.root_positions.shape == (seq.num_frames, 3) and not res.focal_assumed
    np.testing.assert_allclose(res.adjusted, ref["adjusted_3d"], rtol=0, atol=TOL)
    np.testing.assert_allclose(res.root_positions, ref["root_3d"], rtol=0, atol=TOL)
    # The walk moves 3-5 m through space (the capture walks 4.0 m).
    travel = float(np.linalg.norm(res.root_positions[-1] - res.root_positions[0]))
    assert 3.0 <= travel <= 5.0, travel


def test_motion_session_equals_cli_replay_motion(server: Server, tmp_path: Path) -> None:
    example = next(p for p in EXAMPLES if "walk" in p.stem)
    ref, seq = cli_reference(server, example, tmp_path, "replay", "--camera", "--motion")
    rate = float(seq.fps or 0)
    with blapose.Client(server.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size, camera=seq.camera) as s:
            plain = list(s.stream(seq.frames()))
        with client.session(layout=seq.layout, image_size=seq.image_size, camera=seq.camera, motion=rate) as s:
            moved = list(s.stream(seq.frames()))
    assert all(r.root is None and r.world is None for r in plain)
    assert all(r.root is not None and not r.focal_assumed for r in moved)
    np.testing.assert_allclose(np.stack([r.adjusted for r in moved]), ref["adjusted_3d"], rtol=0, atol=TOL)
    np.testing.assert_allclose(np.stack([r.root for r in moved]), ref["root_3d"], rtol=0, atol=TOL)
    # Lengths are the plain session's; the pelvis travels with the walker.
    np.testing.assert_array_equal(np.stack([r.bone_lengths for r in moved]), np.stack([r.bone_lengths for r in plain]))
    travel = float(np.linalg.norm(moved[-1].root - moved[0].root))
    assert 3.0 <= travel <= 5.5, travel
