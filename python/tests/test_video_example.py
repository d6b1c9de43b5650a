"""python/examples/video_to_poses.py end to end: a short video -> MediaPipe -> server lifter -> npz + HTML.

Skipped unless the example's optional dependencies (mediapipe 0.10.21, OpenCV) and
scikit-image (the test video's picture) are installed; see python/examples/README.md.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import blapose
from conftest import REPO

EXAMPLE = REPO / "python" / "examples" / "video_to_poses.py"
LIFTER = REPO / "models" / "lifter_videopose27_causal.safetensors"
FRAMES = 24
BLANK = (5, 6)  # frames with nobody in them: skipped by the example


def _optional_deps():
    try:
        import cv2
        import mediapipe as mp
        import skimage.data
    except ImportError as e:
        pytest.skip(
            f"optional dependency missing ({e}): pip install ./python opencv-python-headless absl-py attrs "
            f"flatbuffers matplotlib scikit-image 'numpy<2' && pip install --no-deps mediapipe==0.10.21"
        )
    if not hasattr(mp, "solutions"):
        pytest.skip(f"mediapipe {mp.__version__} has no legacy solutions: pip install --no-deps mediapipe==0.10.21")
    return cv2, skimage.data


def make_video(path: Path, cv2, data) -> None:
    """FRAMES frames of scikit-image's astronaut (NASA, public domain), drifting a few
    pixels, with two black frames; MJPG in an .avi (OpenCV's own encoder)."""
    im = data.astronaut()
    h, w = im.shape[:2]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (w, h))
    assert out.isOpened()
    for i in range(FRAMES):
        if i in BLANK:
            frame = np.zeros_like(im)
        else:
            shift = np.float32([[1, 0, 3 * np.sin(i / 4)], [0, 1, 2 * np.cos(i / 5)]])
            frame = cv2.warpAffine(im, shift, (w, h), borderMode=cv2.BORDER_REFLECT)
        out.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    out.release()


def run_example(start_server, tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """The example on the test video against a server with the lifter; skips without the optional deps."""
    cv2, data = _optional_deps()
    if not LIFTER.exists():
        pytest.skip(f"{LIFTER} not present")
    video = tmp_path / "astronaut.avi"
    make_video(video, cv2, data)
    srv = start_server("--lifter-weights", str(LIFTER))
    return subprocess.run(
        [sys.executable, str(EXAMPLE), str(video), "--server", srv.url, *args],
        check=False, capture_output=True, text=True, timeout=300,
    )  # fmt: skip


def test_video_to_poses_end_to_end(start_server, tmp_path: Path) -> None:
    npz, html, bvh = tmp_path / "poses.npz", tmp_path / "report.html", tmp_path / "motion.bvh"
    run = run_example(start_server, tmp_path, "--out", str(npz), "--html", str(html), "--bvh", str(bvh),
                      "--max-frames", str(FRAMES - 2))  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert f"{FRAMES - 2} frames read" in run.stdout

    replay = blapose.load_replay(npz)  # the format blapose-client replay reads
    t = replay.num_frames
    assert t == FRAMES - 2 - len(BLANK)  # the astronaut is found in every other frame
    assert replay.layout == "coco17" and replay.image_size == (512, 512) and replay.fps == 25.0
    assert replay.keypoints_2d.shape == (t, 17, 2) and replay.pose_3d.shape == (t, 17, 3)
    assert replay.confidence is not None and replay.confidence.shape == (t, 17)
    with np.load(npz) as z:
        adjusted, lengths, frame, root = z["adjusted_3d"], z["bone_lengths"], z["video_frame"], z["root_3d"]
    assert adjusted.shape == (t, 17, 3) and lengths.shape == (t, 16) and root.shape == (t, 3)
    # The motion stage (on by default) placed the pelvis in front of the camera.
    assert np.all(np.isfinite(root)) and np.all(root[:, 2] > 0.5)
    assert "motion: the pelvis travelled" in run.stdout
    assert not set(BLANK) & set(frame.astype(int).tolist())
    for a in (replay.keypoints_2d, replay.pose_3d, replay.confidence, adjusted, lengths):
        assert np.all(np.isfinite(a))
    assert np.all((replay.confidence >= 0) & (replay.confidence <= 1))
    # The face is in the top half of the picture, the shoulders below it.
    nose, shoulders = replay.keypoints_2d[:, 0], replay.keypoints_2d[:, 5:7]
    assert np.all(nose[:, 1] < 256) and np.all(shoulders[:, :, 1] > nose[:, None, 1])
    assert np.all((lengths > 0.02) & (lengths < 1.0))
    # The motion stage smooths directions only: every adjusted pose has the estimated lengths.
    parents = np.asarray(blapose.PARENTS[1:])  # bone i ends at joint i + 1
    for k in range(t):
        measured = np.linalg.norm(adjusted[k, 1:] - adjusted[k, parents], axis=1)
        np.testing.assert_allclose(measured, lengths[k], atol=1e-4)

    # The BVH: the placed motion re-posed with the final lengths (what tests/export/ checks
    # in Blender); its text is what blapose.export writes for those arrays.
    assert "every frame re-posed with the final bone lengths" in run.stdout
    text, _ = blapose.export.bvh_text(adjusted + root[:, None, :], lengths, fps=25.0)
    assert bvh.read_text() == text

    report = blapose.report.read_html_data(html)
    assert report["frames"] == t
    # the page prints "frames: T" itself; the header lines do not repeat it
    assert [k for k, _ in report["info"]] == ["lifter", "detector", "video", "motion"]
    np.testing.assert_allclose(np.reshape(report["root"], (t, 3)), root, atol=1e-4)
    assert dict(report["info"])["video"] == f"{FRAMES - 2} frames read, {t} with a person"
    assert np.asarray(report["before"]).size == t * 17 * 3 and np.asarray(report["after"]).size == t * 17 * 3


def test_video_to_poses_without_motion(start_server, tmp_path: Path) -> None:
    npz = tmp_path / "poses.npz"
    run = run_example(start_server, tmp_path, "--out", str(npz), "--no-motion", "--max-frames", "12")
    assert run.returncode == 0, run.stderr
    replay = blapose.load_replay(npz)
    with np.load(npz) as z:
        assert "root_3d" not in z.files
        adjusted, lengths = z["adjusted_3d"], z["bone_lengths"]
    # adjusted = the lifted pose's bone directions with the estimated lengths (root kept).
    for k in (0, replay.num_frames - 1):
        np.testing.assert_allclose(adjusted[k], blapose.adjust_pose(replay.pose_3d[k], lengths[k]), atol=1e-4)
