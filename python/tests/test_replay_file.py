"""load_replay refuses hostile and malformed replay files by name, and never
inflates more than the arrays it returns (no server needed)."""

import io
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

import blapose
from blapose import ReplayFileError, load_replay

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "cmu_02_02_walk.npz"


def arrays(frames=100, joints=17):
    rng = np.random.default_rng(0)
    return {
        "keypoints_2d": rng.uniform(0, 1000, (frames, joints, 2)).astype(np.float32),
        "pose_3d": rng.normal(0, 0.3, (frames, 17, 3)).astype(np.float32),
        "image_size": np.array([1000, 1000], np.float32),
    }


def write(tmp_path, members, name="r.npz"):
    path = tmp_path / name
    np.savez(path, **members)
    return path


def refused(path, key, *fragments, **kwargs):
    with pytest.raises(ReplayFileError) as info:
        load_replay(path, **kwargs)
    assert info.value.key == key, str(info.value)
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)
    return info.value


def test_the_examples_load_as_before():
    seq = load_replay(EXAMPLE)
    with np.load(EXAMPLE) as z:
        assert np.array_equal(seq.keypoints_2d, z["keypoints_2d"].astype(np.float32))
        assert np.array_equal(seq.pose_3d, z["pose_3d"].astype(np.float32))
    assert seq.layout == "h36m17" and seq.num_frames == len(seq.pose_3d)
    seq.keypoints_2d[0, 0, 0] += 1.0  # arrays are writable, as np.load's are


def test_shapes_and_values_are_checked_by_name(tmp_path):
    a = arrays()
    refused(write(tmp_path, {**a, "pose_3d": arrays(124)["pose_3d"]}), "pose_3d", "(124, 17, 3)", "(100, 17, 3)")
    refused(write(tmp_path, {**a, "keypoints_2d": a["pose_3d"]}), "keypoints_2d", "(100, 17, 3)", "(T, J, 2)")
    refused(write(tmp_path, {**a, "keypoints_2d": np.zeros((0, 17, 2), np.float32)}), "keypoints_2d", "T: frames")
    bad = a["keypoints_2d"].copy()
    bad[7, 3, 1] = np.nan
    refused(write(tmp_path, {**a, "keypoints_2d": bad}), "keypoints_2d", "frame 7, joint 3")
    refused(write(tmp_path, {k: v for k, v in a.items() if k != "pose_3d"}), "pose_3d", "missing")
    refused(write(tmp_path, {**a, "image_size": np.array([0.5, 10], np.float32)}), "image_size")
    refused(write(tmp_path, {**a, "layout": np.array([9.0])}), "layout", "unknown")
    refused(write(tmp_path, {**a, "confidence": np.full((100, 17), -1.0)}), "confidence", "negative")
    refused(write(tmp_path, {**a, "camera_up": np.array([0.0, -1.0, 0.0])}), "camera_focal", "come together")
    refused(write(tmp_path, {**a, "keypoints_2d": np.array([["x"] * 2] * 17 * 100).reshape(100, 17, 2)}), "keypoints_2d", "dtype")
    refused(write(tmp_path, a), "keypoints_2d", "T: frames, 1 to 50", max_frames=50)


def test_a_file_that_is_not_an_npz_is_named_as_such(tmp_path):
    path = tmp_path / "not.npz"
    path.write_bytes(b"\x80\x04 not a zip at all")
    err = refused(path, None, "not a replay file")
    assert "pickle" not in str(err)
    assert isinstance(err, blapose.BlaposeError) and isinstance(err, ValueError)


def npy_header(shape, dtype="<f4"):
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def test_a_zip_bomb_is_refused_before_it_is_inflated(tmp_path):
    """A member declaring 2 GB is refused from its header; an unused huge
    member is never read; peak memory stays near the returned arrays."""
    path = tmp_path / "bomb.npz"
    a = arrays()
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for key in ("pose_3d", "image_size"):
            z.writestr(key + ".npy", npy_header(a[key].shape) + a[key].tobytes())
        # keypoints declaring 2**31 / 136 frames: refused before a byte of data is read
        z.writestr("keypoints_2d.npy", npy_header((15_790_321, 17, 2)) + bytes(1 << 20))
    refused(path, "keypoints_2d", "T: frames")

    path = tmp_path / "unused.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for key, value in a.items():
            z.writestr(key + ".npy", npy_header(value.shape) + value.tobytes())
        with z.open("junk.npy", "w", force_zip64=True) as member:
            member.write(npy_header((64 << 20,), "|u1"))
            chunk = bytes(1 << 20)
            for _ in range(64):
                member.write(chunk)
    assert path.stat().st_size < 2 << 20
    tracemalloc.start()
    seq = load_replay(path)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    returned = seq.keypoints_2d.nbytes + seq.pose_3d.nbytes
    assert peak < 2 * returned + (1 << 20), (peak, returned)


def test_a_zip_directory_bomb_is_refused_before_it_is_parsed(tmp_path):
    """zipfile reads the whole directory when it opens an archive: too many
    entries, or a directory too large, are refused from the end record."""
    a = arrays()
    path = write(tmp_path, a, "entries.npz")
    with zipfile.ZipFile(path, "a") as z:
        for i in range(blapose.replay_file.MAX_ENTRIES):
            z.writestr(f"j{i}.npy", b"")
    tracemalloc.start()
    err = refused(path, None, "entries", str(blapose.replay_file.MAX_ENTRIES))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 1 << 20, (peak, str(err))

    path = write(tmp_path, a, "names.npz")
    with zipfile.ZipFile(path, "a") as z:
        for i in range(200):
            z.writestr(f"{i:08000d}.npy", b"")
    refused(path, None, "bytes")
    # A file just within both limits still loads.
    path = write(tmp_path, a, "fine.npz")
    with zipfile.ZipFile(path, "a") as z:
        for i in range(blapose.replay_file.MAX_ENTRIES - len(a)):
            z.writestr(f"j{i}.npy", b"")
    assert load_replay(path).num_frames == 100


def member_data(path, key):
    """Offset and length of member ``key``'s stored (maybe compressed) bytes."""
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(key + ".npy")
    raw = path.read_bytes()
    at = info.header_offset
    name_len, extra_len = int.from_bytes(raw[at + 26 : at + 28], "little"), int.from_bytes(raw[at + 28 : at + 30], "little")
    return at + 30 + name_len + extra_len, info.compress_size


@pytest.mark.parametrize("compressed", [False, True])
def test_a_corrupt_member_is_a_replay_file_error(tmp_path, compressed):
    """A bad CRC (stored member) or a corrupt deflate stream (zlib.error
    inside zipfile) is a ReplayFileError naming the member."""
    path = tmp_path / "corrupt.npz"
    (np.savez_compressed if compressed else np.savez)(path, **arrays())
    start, length = member_data(path, "pose_3d")
    raw = bytearray(path.read_bytes())
    for i in range(start + length // 2, start + length // 2 + 16):
        raw[i] ^= 0x5A
    path.write_bytes(bytes(raw))
    err = refused(path, "pose_3d", "cannot be read")
    assert isinstance(err, ValueError)
