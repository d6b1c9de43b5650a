"""Detector confidences: a joint below ``blapose.MISSING_CONFIDENCE`` is missing,
its keypoint is not read (NaN is fine), and a frame without a detected joint
leaves the estimate as it stood; and a known height."""

from __future__ import annotations

import blapose
import numpy as np
from conftest import EXAMPLES, Server


def _frames(garbage: float):
    seq = blapose.load_replay(EXAMPLES[0])
    frames = []
    for t, (kp, pose) in enumerate(zip(seq.keypoints_2d, seq.pose_3d)):
        kp = np.array(kp, dtype=np.float32)
        conf = np.ones(kp.shape[0], np.float32)
        if t % 4 == 1:
            conf[(3 * t) % kp.shape[0]] = 0.0
            kp[(3 * t) % kp.shape[0]] = garbage
        if t == 9:
            conf[:] = 0.0
            kp[:] = garbage
        frames.append((kp, pose, conf))
    return seq, frames


def _run(server: Server, garbage: float):
    seq, frames = _frames(garbage)
    with blapose.Client(server.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size) as s:
            results = list(s.stream(frames))
            s.close()
        offline = client.adjust_sequence(
            np.stack([f[0] for f in frames]),
            seq.pose_3d,
            layout=seq.layout,
            image_size=seq.image_size,
            confidence=np.stack([f[2] for f in frames]),
        )
    return results, offline


def test_missing_keypoints_are_not_read(server: Server) -> None:
    assert blapose.MISSING_CONFIDENCE == 0.1
    nan, nan_offline = _run(server, float("nan"))
    big, big_offline = _run(server, 5000.0)
    assert len(nan) == len(big) > 10
    for a, b in zip(nan, big):
        np.testing.assert_array_equal(a.bone_lengths, b.bone_lengths)
        np.testing.assert_array_equal(a.adjusted, b.adjusted)
    np.testing.assert_array_equal(nan_offline.bone_lengths, big_offline.bone_lengths)
    # The frame without a detected joint: the estimate as it stood, counted.
    np.testing.assert_array_equal(nan[9].bone_lengths, nan[8].bone_lengths)
    assert nan[9].frames_seen == 10


def test_a_known_height_gives_the_stature_regressions_lengths(server: Server) -> None:
    """With the person's height (and sex), sessions and AdjustSequence answer
    with the stature regression's lengths; a height out of range is refused."""
    import json
    from pathlib import Path

    model = json.loads((Path(__file__).resolve().parents[2] / "models" / "stature_regression.json").read_text())
    line = model["female"]
    want = np.array([a + s * np.float32(1.62) for a, s in zip(line["intercept"], line["slope"])], np.float32)
    seq = blapose.load_replay(EXAMPLES[0])
    with blapose.Client(server.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size, height=1.62, sex="female") as s:
            results = list(s.stream(seq.frames()))
            s.close()
        offline = client.adjust_sequence(
            seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size, height=1.62, sex="female"
        )
        for r in results:
            np.testing.assert_allclose(r.bone_lengths, want, atol=1e-6)
        np.testing.assert_allclose(offline.bone_lengths, np.tile(want, (seq.num_frames, 1)), atol=1e-6)
        try:
            client.adjust_sequence(seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size, height=0.5)
        except blapose.InvalidArgument as e:
            assert "subject.height_m" in str(e)
        else:
            raise AssertionError("a height of 0.5 m was accepted")
