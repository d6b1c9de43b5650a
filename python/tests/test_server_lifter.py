"""Keypoints-only sessions (server_lifter=True) equal `blapose-client replay --server-lifter`."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

import blapose
from conftest import CLIENT_BIN, EXAMPLES, REPO

LIFTER = REPO / "models" / "lifter_videopose27_causal.safetensors"
TOL = 1e-5


def test_server_lifter_equals_cli(start_server, tmp_path: Path) -> None:
    if not LIFTER.exists():
        pytest.skip(f"{LIFTER} not present")
    srv = start_server("--lifter-weights", str(LIFTER))
    example = EXAMPLES[1]
    out = tmp_path / "cli.npz"
    subprocess.run(
        [str(CLIENT_BIN), "--server", srv.url, "replay", str(example), "--server-lifter", "--out", str(out)],
        check=True, capture_output=True, timeout=120,
    )  # fmt: skip
    ref = np.load(out)
    seq = blapose.load_replay(example)
    with blapose.Client(srv.url) as client:
        assert client.info().lifter is not None
        with client.session(layout=seq.layout, image_size=seq.image_size, server_lifter=True) as s:
            assert s.info.lifter
            first = s.send(seq.keypoints_2d[0])
            rest = list(s.stream(seq.keypoints_2d[1:]))
            with pytest.raises(ValueError):
                s.send(seq.keypoints_2d[0], seq.pose_3d[0])  # keypoints only
    results = [first] + rest
    assert all(r.lifter == s.info.lifter and r.lifted is not None for r in results)
    np.testing.assert_allclose(np.stack([r.adjusted for r in results]), ref["adjusted_3d"], rtol=0, atol=TOL)
    np.testing.assert_allclose(np.stack([r.bone_lengths for r in results]), ref["bone_lengths"], rtol=0, atol=TOL)
    np.testing.assert_allclose(np.stack([r.lifted for r in results]), ref["lifted_3d"], rtol=0, atol=TOL)
