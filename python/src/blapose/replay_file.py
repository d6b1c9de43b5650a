"""Replay files (``.npz``), read safely.

A replay file comes from anywhere (a colleague, a download, a fuzzer), and an
``.npz`` is a zip archive whose members declare their own size: a 2 MB file
can inflate to gigabytes, and ``np.load`` inflates whatever is asked of it.
So this reader opens only the members the format defines, reads each one's
``.npy`` header first, checks its dtype and shape against the format (every
per-frame array has the keypoints' frame count, which is bounded by
``max_frames``) and only then reads exactly the declared bytes, and one more
to prove the member ends there (which also checks its CRC). The memory it uses
is about the size of the arrays it returns. The zip directory is bounded too:
``zipfile`` reads the whole central directory into memory when it opens an
archive, so the end-of-directory record ``zipfile`` itself would use is read
first and an archive declaring more than :data:`MAX_ENTRIES` entries or a
directory over :data:`MAX_DIRECTORY_BYTES` is refused before it is parsed (a
replay file has about fifteen members; a 415 MB file with 8 M entries made
``zipfile`` take 3.7 GB). Every refusal, a corrupt or truncated member included,
is a :class:`ReplayFileError` naming the key, what was expected and what was
found.

The format (the same as ``blapose-client replay`` reads; see client/README.md):

================== ============== ==========================================
key                shape          meaning
================== ============== ==========================================
keypoints_2d       (T, J, 2)      pixels, J = 17 (h36m17, coco17) or 16 (sh16)
pose_3d            (T, 17, 3)     the lifter's poses, metres
image_size         (2,)           width, height in pixels (whole, >= 1)
layout             (1,)           optional: 1 h36m17, 2 sh16, 3 coco17
gt_3d              (T, 17, 3)     optional ground truth, metres
confidence         (T, J)         optional, finite and >= 0
fps                (1,)           optional frame rate
camera_up          (3,)           optional calibration (with focal, principal)
camera_focal       (2,)
camera_principal   (2,)
camera_height      (1,)           optional, metres
camera_distortion  (4,) or (5,)   optional OpenCV k1 k2 p1 p2 [k3]
================== ============== ==========================================
"""

from __future__ import annotations

import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from .errors import BlaposeError
from .types import LAYOUTS, Camera, _LAYOUT_BY_VALUE

__all__ = ["ReplayFile", "ReplayFileError", "load_replay", "DEFAULT_MAX_FRAMES", "MAX_ENTRIES", "MAX_DIRECTORY_BYTES"]

#: The most frames :func:`load_replay` accepts by default (an hour at 250 fps;
#: about 350 MB of keypoints and poses).
DEFAULT_MAX_FRAMES = 900_000

#: The most zip directory entries a replay file may declare (``blapose-client``
#: has the same limit).
MAX_ENTRIES = 1024
#: The most bytes a replay file's zip directory may declare.
MAX_DIRECTORY_BYTES = 1 << 20

# What reading a damaged archive or member raises, besides ReplayFileError:
# zipfile's own errors, a corrupt deflate stream (zlib.error), a truncated
# file, a truncated record (struct.error), an unsupported compression method
# (NotImplementedError) or an encrypted member (RuntimeError).
_MALFORMED = (zipfile.BadZipFile, zlib.error, ValueError, EOFError, OSError, struct.error, NotImplementedError, RuntimeError)

# Shapes: ints are fixed, "T" is the frame count, "J" the joint count.
_KEYPOINTS = "keypoints_2d"
_SMALL_MEMBERS = {
    "image_size": ((2,),),
    "layout": ((1,),),
    "fps": ((1,),),
    "camera_up": ((3,),),
    "camera_focal": ((2,),),
    "camera_principal": ((2,),),
    "camera_height": ((1,),),
    "camera_distortion": ((4,), (5,)),
}
_CAMERA_KEYS = ("camera_up", "camera_focal", "camera_principal")


class ReplayFileError(BlaposeError, ValueError):
    """A replay file that cannot be read: not an ``.npz``, a missing key, or an
    array of the wrong dtype, shape or values.

    Attributes:
        path: the file.
        key: the array at fault (None when the file itself is).
        problem: what is wrong, with what was expected.
    """

    def __init__(self, path: Union[str, Path], key: Optional[str], problem: str) -> None:
        self.path = str(path)
        self.key = key
        self.problem = problem
        where = f"{self.path}: {key}" if key else self.path
        super().__init__(f"{where}: {problem}")


@dataclass
class ReplayFile:
    """A replay ``.npz`` as ``blapose-client replay`` reads it (see client/README.md)."""

    keypoints_2d: np.ndarray  # (T, J, 2)
    pose_3d: np.ndarray  # (T, 17, 3)
    image_size: Tuple[int, int]
    layout: str
    gt_3d: Optional[np.ndarray] = None
    confidence: Optional[np.ndarray] = None
    fps: Optional[float] = None
    camera: Optional[Camera] = None

    @property
    def num_frames(self) -> int:
        return int(self.keypoints_2d.shape[0])

    def frames(self):
        """``(keypoints, pose)`` pairs, ready for :meth:`blapose.Session.stream`."""
        return zip(self.keypoints_2d, self.pose_3d)


def _shape_text(shape: Sequence[Union[int, str]]) -> str:
    inner = ", ".join(str(d) for d in shape)
    return f"({inner},)" if len(shape) == 1 else f"({inner})"


class _Archive:
    """The members of one ``.npz``, each read only after its header is checked."""

    def __init__(self, path: Union[str, Path]) -> None:
        self.path = path
        try:
            with open(path, "rb") as f:
                self._check_directory(f)
            self.zip = zipfile.ZipFile(path)
        except (FileNotFoundError, ReplayFileError):
            raise
        except _MALFORMED as e:
            raise ReplayFileError(path, None, f"not a replay file (an .npz zip archive): {e}") from None
        self.names = {n[: -len(".npy")] for n in self.zip.namelist() if n.endswith(".npy")}

    def _check_directory(self, f) -> None:
        # The end-of-directory record zipfile.ZipFile reads (zip64 included):
        # the directory it then reads into memory is the size this declares.
        end = zipfile._EndRecData(f)
        if end is None:
            raise self.fail(None, "not a replay file (an .npz zip archive): no zip end-of-directory record")
        entries, size = end[zipfile._ECD_ENTRIES_TOTAL], end[zipfile._ECD_SIZE]
        if entries > MAX_ENTRIES:
            raise self.fail(None, f"its zip directory declares {entries} entries, more than the {MAX_ENTRIES} a replay file may have")
        if size > MAX_DIRECTORY_BYTES:
            raise self.fail(None, f"its zip directory declares {size} bytes, more than the {MAX_DIRECTORY_BYTES} a replay file's may take")

    def __enter__(self) -> "_Archive":
        return self

    def __exit__(self, *exc) -> None:
        self.zip.close()

    def __contains__(self, key: str) -> bool:
        return key in self.names

    def fail(self, key: Optional[str], problem: str) -> ReplayFileError:
        return ReplayFileError(self.path, key, problem)

    def read(self, key: str, shapes: Sequence[Tuple[Union[int, str], ...]], dims: dict) -> np.ndarray:
        """Member ``key`` as float32, refused unless its shape is one of
        ``shapes`` (``"T"`` and ``"J"`` resolved through ``dims``; an
        unresolved ``"T"`` is bounded by ``dims["max_frames"]``)."""
        if key not in self.names:
            raise self.fail(key, "is missing")
        try:
            with self.zip.open(key + ".npy") as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise self.fail(key, f"unsupported .npy version {version}")
                if dtype.kind not in "fiu" or dtype.hasobject:
                    raise self.fail(key, f"has dtype {dtype}; expected a numeric array (float or int)")
                expected = " or ".join(_shape_text([dims.get(d, d) if isinstance(d, str) else d for d in s]) for s in shapes)
                if not any(self._matches(shape, s, dims) for s in shapes):
                    legend = []
                    if "T" not in dims and any("T" in s for s in shapes):
                        legend.append(f"T: frames, 1 to {dims['max_frames']}")
                    if "J" not in dims and any("J" in s for s in shapes):
                        legend.append("J: 16 or 17 joints")
                    note = f" ({'; '.join(legend)})" if legend else ""
                    raise self.fail(key, f"has shape {_shape_text(shape)}; expected {expected}{note}")
                count = int(np.prod(shape, dtype=np.int64))
                buffer = bytearray(count * dtype.itemsize)
                if f.readinto(buffer) != len(buffer):
                    raise self.fail(key, "is shorter than its header declares")
                # Reading to the member's end checks its CRC.
                if f.read(1):
                    raise self.fail(key, "is longer than its header declares")
        except _MALFORMED as e:
            if isinstance(e, ReplayFileError):
                raise
            raise self.fail(key, f"cannot be read: {e}") from None
        array = np.frombuffer(buffer, dtype=dtype).reshape(shape, order="F" if fortran else "C")
        return np.asarray(array, dtype=np.float32)

    @staticmethod
    def _matches(shape: Tuple[int, ...], pattern: Tuple[Union[int, str], ...], dims: dict) -> bool:
        if len(shape) != len(pattern):
            return False
        for got, want in zip(shape, pattern):
            if isinstance(want, int):
                if got != want:
                    return False
            elif want in dims:
                if got != dims[want]:
                    return False
            elif want == "T":
                if not 1 <= got <= dims["max_frames"]:
                    return False
            elif want == "J":
                if got not in (16, 17):
                    return False
        return True


def _finite(archive: _Archive, key: str, array: np.ndarray) -> np.ndarray:
    bad = ~np.isfinite(array)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        where = f"frame {index[0]}, joint {index[1]}" if len(index) >= 2 else f"value {index[0]}"
        raise archive.fail(key, f"{where} is not finite")
    return array


def load_replay(path: Union[str, Path], max_frames: int = DEFAULT_MAX_FRAMES) -> ReplayFile:
    """Load a replay file (``keypoints_2d``, ``pose_3d``, ``image_size``, optional
    ``layout``, ``gt_3d``, ``confidence``, ``fps``, ``camera_*``), checking every
    array's shape before it is read (see the module docs).

    Raises:
        ReplayFileError: the file is not an ``.npz``, lacks a key, or an array has
            the wrong dtype, shape or values (the message names the key).
        FileNotFoundError: there is no such file.
    """
    with _Archive(path) as z:
        dims: dict = {"max_frames": max_frames}
        kp = z.read(_KEYPOINTS, [("T", "J", 2)], dims)
        frames, joints = kp.shape[0], kp.shape[1]
        dims.update(T=frames)
        if "layout" in z:
            code = float(z.read("layout", _SMALL_MEMBERS["layout"], dims)[0])
            if not code.is_integer() or int(code) not in _LAYOUT_BY_VALUE:
                raise z.fail("layout", f"code {code:g} is unknown (1 = h36m17, 2 = sh16, 3 = coco17)")
            layout = _LAYOUT_BY_VALUE[int(code)]
            if LAYOUTS[layout][1] != joints:
                raise z.fail(_KEYPOINTS, f"has {joints} joints per frame but layout {layout} has {LAYOUTS[layout][1]}")
        else:
            layout = {17: "h36m17", 16: "sh16"}[joints]
        dims.update(J=joints)
        _finite(z, _KEYPOINTS, kp)
        pose = _finite(z, "pose_3d", z.read("pose_3d", [("T", 17, 3)], dims))
        size = z.read("image_size", _SMALL_MEMBERS["image_size"], dims)
        if not all(np.isfinite(v) and v >= 1 and float(v).is_integer() for v in size):
            raise z.fail("image_size", f"is {size.tolist()}; expected two whole numbers of pixels >= 1")
        gt = _finite(z, "gt_3d", z.read("gt_3d", [("T", 17, 3)], dims)) if "gt_3d" in z else None
        confidence = None
        if "confidence" in z:
            confidence = _finite(z, "confidence", z.read("confidence", [("T", "J")], dims))
            if (confidence < 0).any():
                t, j = (int(i) for i in np.argwhere(confidence < 0)[0])
                raise z.fail("confidence", f"frame {t}, joint {j} is negative")
        fps = None
        if "fps" in z:
            fps = float(_finite(z, "fps", z.read("fps", _SMALL_MEMBERS["fps"], dims))[0])
        camera = _camera(z, dims)
        return ReplayFile(
            keypoints_2d=kp,
            pose_3d=pose,
            image_size=(int(size[0]), int(size[1])),
            layout=layout,
            gt_3d=gt,
            confidence=confidence,
            fps=fps,
            camera=camera,
        )


def _camera(z: _Archive, dims: dict) -> Optional[Camera]:
    present = [k for k in (*_CAMERA_KEYS, "camera_height", "camera_distortion") if k in z]
    if not present:
        return None
    missing = [k for k in _CAMERA_KEYS if k not in z]
    if missing:
        raise z.fail(
            missing[0],
            "is missing: camera_up, camera_focal and camera_principal come together, "
            f"and camera_height needs them (found {', '.join(present)})",
        )
    values = {k: _finite(z, k, z.read(k, _SMALL_MEMBERS[k], dims)) for k in present}
    return Camera(
        up=tuple(float(v) for v in values["camera_up"]),  # type: ignore[arg-type]
        focal=tuple(float(v) for v in values["camera_focal"]),  # type: ignore[arg-type]
        principal=tuple(float(v) for v in values["camera_principal"]),  # type: ignore[arg-type]
        height=float(values["camera_height"][0]) if "camera_height" in values else None,
        distortion=tuple(float(v) for v in values["camera_distortion"]) if "camera_distortion" in values else None,
    )
