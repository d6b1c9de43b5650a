"""blapose.report: the HTML report, and the same page from `blapose-client replay --html`."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import blapose
import numpy as np
import pytest
from blapose import report
from conftest import CLIENT_BIN, EXAMPLES, Server

ROUNDING = 0.5e-4 + 1e-9  # metres: the page holds poses rounded to 0.1 mm


def _example():
    seq = blapose.load_replay(EXAMPLES[0])
    lengths = np.median(np.linalg.norm(seq.gt_3d[:, 1:] - seq.gt_3d[:, list(blapose.PARENTS[1:])], axis=-1), axis=0)
    after = np.stack([blapose.adjust_pose(p, lengths) for p in seq.pose_3d])
    return seq, after


def _flat(data: dict, key: str) -> np.ndarray:
    return np.asarray(data[key], dtype=np.float64).reshape(data["frames"], 17, 3)


def test_template_is_shipped_with_one_placeholder() -> None:
    page = report.template()
    assert page.count(report.DATA_PLACEHOLDER) == 1
    assert page.count('<script id="blapose-data"') == 1
    assert "http://" not in page and "https://" not in page


def test_write_html_round_trips(tmp_path: Path) -> None:
    seq, after = _example()
    out = report.write_html(
        tmp_path / "r.html",
        seq.pose_3d,
        after,
        gt=seq.gt_3d,
        fps=seq.fps,
        title="walk",
        info={"model": "median gt"},
        up=seq.camera.up,
    )
    html = out.read_text(encoding="utf-8")
    assert report.DATA_PLACEHOLDER not in html
    data = report.read_html_data(out)
    assert data["format"] == report.FORMAT == "blapose-report/1"
    assert data["frames"] == seq.num_frames and data["fps"] == 50.0 and data["title"] == "walk"
    assert data["skeleton"] == {
        "joint_names": list(blapose.JOINT_NAMES),
        "bone_names": list(blapose.BONE_NAMES),
        "parents": list(blapose.PARENTS),
    }
    np.testing.assert_allclose(_flat(data, "before"), seq.pose_3d, rtol=0, atol=ROUNDING)
    np.testing.assert_allclose(_flat(data, "after"), after, rtol=0, atol=ROUNDING)
    np.testing.assert_allclose(_flat(data, "gt"), seq.gt_3d, rtol=0, atol=ROUNDING)
    assert data["info"] == [["model", "median gt"]]
    np.testing.assert_allclose(data["up"], seq.camera.up)
    m = data["metrics"]
    assert m["frames"] == seq.num_frames
    assert m["after"]["bone_error_mm"] < m["before"]["bone_error_mm"]
    assert 0 < m["before"]["p_mpjpe_mm"] < m["before"]["mpjpe_mm"]
    # Without ground truth: no gt, no table.
    data = report.read_html_data(report.render_html(seq.pose_3d, after, fps=None))
    assert data["gt"] is None and data["metrics"] is None and data["fps"] is None


def test_strings_cannot_close_the_script_element(tmp_path: Path) -> None:
    seq, after = _example()
    evil = "</script><script>alert(1)</script><!--"
    html = report.render_html(seq.pose_3d, after, title=evil, info=[("a</b", evil)])
    start = html.index('<script id="blapose-data"')
    end = html.index("</script>", start)
    assert "</" not in html[start + 1 : end] and "<!--" not in html[start:end]
    data = report.read_html_data(html)
    assert data["title"] == evil and data["info"] == [["a</b", evil]]


def test_bad_input_raises_value_error() -> None:
    seq, after = _example()
    with pytest.raises(ValueError, match=r"before must have shape \(T, 17, 3\)"):
        report.render_html(seq.pose_3d[:, :16], after)
    with pytest.raises(ValueError, match="after has 10 frames but before has"):
        report.render_html(seq.pose_3d, after[:10])
    with pytest.raises(ValueError, match="gt"):
        report.render_html(seq.pose_3d, after, gt=seq.gt_3d[:5])
    with pytest.raises(ValueError, match="no frames"):
        report.render_html(np.zeros((0, 17, 3)), np.zeros((0, 17, 3)))
    bad = after.copy()
    bad[3, 7, 1] = np.nan
    with pytest.raises(ValueError, match="frame 3, joint 7 is not finite"):
        report.render_html(seq.pose_3d, bad)
    with pytest.raises(ValueError, match="fps"):
        report.render_html(seq.pose_3d, after, fps=0)
    with pytest.raises(ValueError, match="up"):
        report.render_html(seq.pose_3d, after, up=(0, 0, 0))


def test_metrics_match_the_client_definition() -> None:
    seq, _ = _example()
    same = report.metrics(seq.gt_3d + 1.0, seq.gt_3d)  # translation is ignored
    assert max(same.values()) < 1e-3  # mm (float32 inputs)
    scaled = report.metrics(seq.gt_3d * 1.1, seq.gt_3d)
    assert scaled["p_mpjpe_mm"] < 1e-3  # a similarity aligns it exactly
    mirrored = seq.gt_3d * np.array([-1.0, 1.0, 1.0])  # no reflection in the alignment
    assert report.metrics(mirrored, seq.gt_3d)["p_mpjpe_mm"] > 1.0


def _cli(server: Server, *args: str) -> str:
    if not CLIENT_BIN.exists():
        pytest.fail(f"{CLIENT_BIN} is missing: cargo build --release -p blapose-server -p blapose-client")
    done = subprocess.run(
        [str(CLIENT_BIN), "--server", server.url, *args], check=True, capture_output=True, timeout=120, text=True
    )
    return done.stdout


def test_python_and_cli_reports_carry_the_same_data(server: Server, tmp_path: Path) -> None:
    example = EXAMPLES[0]
    rust_path = tmp_path / "rust.html"
    stdout = _cli(server, "replay", str(example), "--html", str(rust_path), "--json", str(tmp_path / "m.json"))
    assert f"wrote {rust_path}" in stdout
    rust = report.read_html_data(rust_path)
    seq = blapose.load_replay(example)
    with blapose.Client(server.url) as client:
        with client.session(layout=seq.layout, image_size=seq.image_size) as s:
            results = list(s.stream(seq.frames()))
    py_path = blapose.write_replay_html(tmp_path / "py.html", seq, results, title=example.name)
    py = report.read_html_data(py_path)
    # One template: the pages differ only in their data.
    data = re.compile(r'(<script id="blapose-data" type="application/json">).*?(</script>)', re.DOTALL)
    pages = [data.sub(r"\1\2", p.read_text(encoding="utf-8")) for p in (rust_path, py_path)]
    assert pages[0] == pages[1]
    for key in ("format", "frames", "fps", "skeleton", "title"):
        assert py[key] == rust[key], key
    np.testing.assert_allclose(py["up"], rust["up"], rtol=0, atol=1e-6)
    for key in ("before", "after", "gt"):
        # Both round to 0.1 mm; the answers agree to 1e-5 m, so a rounding may differ by one step.
        np.testing.assert_allclose(_flat(py, key), _flat(rust, key), rtol=0, atol=1e-4 + 1e-9, err_msg=key)
    # The table: the CLI's (blapose_core::metrics::evaluate, also in --json) and Python's numpy twin.
    cli_json = json.loads((tmp_path / "m.json").read_text())
    assert rust["metrics"] == cli_json
    for side in ("before", "after"):
        for k in ("mpjpe_mm", "p_mpjpe_mm", "bone_error_mm"):
            assert py["metrics"][side][k] == pytest.approx(rust["metrics"][side][k], abs=0.02), (side, k)
    header = dict(rust["info"])
    assert header["model"] == "gru (default, stream)"
    assert header["server"].startswith(server.url)


def test_adjust_html_from_the_cli(server: Server, tmp_path: Path) -> None:
    out = tmp_path / "adjust.html"
    _cli(server, "adjust", str(EXAMPLES[1]), "--html", str(out))
    data = report.read_html_data(out)
    assert dict(data["info"])["model"] == "bigru (default, offline call)"
    seq = blapose.load_replay(EXAMPLES[1])
    with blapose.Client(server.url) as client:
        res = client.adjust_sequence(seq.keypoints_2d, seq.pose_3d, layout=seq.layout, image_size=seq.image_size)
    py = report.read_html_data(blapose.write_replay_html(tmp_path / "py.html", seq, res))
    assert dict(py["info"])["model"] == "bigru"
    np.testing.assert_allclose(_flat(py, "after"), _flat(data, "after"), rtol=0, atol=1e-4 + 1e-9)


def test_root_path_round_trips_and_bad_roots_are_refused() -> None:
    seq, after = _example()
    root = np.cumsum(np.full((seq.num_frames, 3), [0.01, 0.0, 0.002]), axis=0) + [0.0, 0.0, 4.0]
    data = report.read_html_data(report.render_html(seq.pose_3d, after, root=root))
    np.testing.assert_allclose(np.reshape(data["root"], (-1, 3)), root, rtol=0, atol=1e-4)
    assert report.read_html_data(report.render_html(seq.pose_3d, after))["root"] is None
    for bad in (root[1:], np.full_like(root, np.nan)):
        with pytest.raises(ValueError, match="root"):
            report.render_html(seq.pose_3d, after, root=bad)
