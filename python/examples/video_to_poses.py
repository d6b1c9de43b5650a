#!/usr/bin/env python3
"""A video file -> 2D keypoints (MediaPipe Pose) -> 3D poses with adjusted bone lengths.

    python video_to_poses.py VIDEO --server http://127.0.0.1:50051 \\
        --out poses.npz --html report.html [--bvh motion.bvh] [--c3d motion.c3d] [--max-frames N]

1. reads the video's frames with OpenCV;
2. detects 2D keypoints with MediaPipe's legacy Pose solution
   (``model_complexity=1``: its two models ship inside the mediapipe wheel, so
   nothing is downloaded at run time);
3. maps MediaPipe's 33 landmarks to COCO-17, in pixels, with each landmark's
   ``visibility`` as its confidence;
4. streams them through a blapose session: by default the server lifts them
   (its embedded ``models/lifter_videopose27_causal.safetensors``, or
   ``--lifter-weights``), or your own lifter
   (``--lifter MODULE:FUNCTION``, or ``lifter=`` in :func:`video_to_poses`):
   a callable ``f(keypoints, confidence, image_size) -> (17, 3)`` pose, metres,
   Human3.6M joint order, where ``keypoints`` is the frame's ``(17, 2)`` COCO-17
   pixels and ``confidence`` its ``(17,)`` visibilities;
   with the server's causal motion stage (``--no-motion`` turns it off): bone
   directions smoothed and the pelvis placed in camera space through a focal
   length assumed from the image size;
5. writes the replay ``.npz`` (the format ``blapose-client replay`` and
   ``blapose.load_replay`` read; ``pose_3d`` is the lifter's pose, ``root_3d``
   the placed pelvis), the HTML report (lifted vs adjusted, and the pelvis path
   seen from above) and, with ``--bvh`` / ``--c3d``, the adjusted motion for
   Blender and biomechanics tools (``blapose.write_bvh``, ``blapose.write_c3d``:
   every frame re-posed with the final bone lengths and moved to its placed
   pelvis, so the person travels; camera axes made Y up / Z up).

Frames in which MediaPipe finds nobody are skipped: they are not sent (every
frame sent must hold finite keypoints), and the ``video_frame`` array of the
``.npz`` gives the video frame number of each frame kept. The server lifter's
window is the session's last frames sent, so long gaps join motion across them.

Install (see README.md beside this file for why it takes two commands)::

    pip install ./python opencv-python-headless absl-py attrs flatbuffers matplotlib "numpy<2"
    pip install --no-deps mediapipe==0.10.21
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, List, Optional, Tuple

import numpy as np

import blapose

INSTALL_HINT = (
    "pip install ./python opencv-python-headless absl-py attrs flatbuffers matplotlib 'numpy<2'\n"
    "    pip install --no-deps mediapipe==0.10.21"
)

# MediaPipe Pose landmark index of each COCO-17 joint, in COCO order.
COCO_FROM_MEDIAPIPE = np.array(
    [
        0,  # nose
        2,  # left eye
        5,  # right eye
        7,  # left ear
        8,  # right ear
        11,  # left shoulder
        12,  # right shoulder
        13,  # left elbow
        14,  # right elbow
        15,  # left wrist
        16,  # right wrist
        23,  # left hip
        24,  # right hip
        25,  # left knee
        26,  # right knee
        27,  # left ankle
        28,  # right ankle
    ]
)

# f(keypoints (17, 2) COCO-17 pixels, confidence (17,), image_size (w, h)) -> (17, 3) pose
Lifter = Callable[[np.ndarray, np.ndarray, Tuple[int, int]], np.ndarray]


class MissingDependency(RuntimeError):
    pass


def _import_cv2():
    try:
        import cv2
    except ImportError as e:
        raise MissingDependency(
            f"OpenCV is not installed ({e}); install the example's dependencies:\n    {INSTALL_HINT}"
        ) from None
    return cv2


def _protobuf_compat(solution_base) -> None:
    """Let mediapipe 0.10.21's legacy solutions run on the protobuf 7 that blapose needs.

    mediapipe 0.10.21 (the last release with ``mp.solutions``) pins protobuf<5, while
    blapose's generated stubs need protobuf>=7. Two protobuf APIs it uses are gone:
    ``MessageFactory.GetPrototype`` (its C++ packet getters call it) and
    ``FieldDescriptor.label`` (read when a solution sets calculator options, e.g.
    ``min_detection_confidence``). Both get equivalent stand-ins; nothing changes
    on a protobuf that still has them.
    """
    from google.protobuf import message_factory

    if not hasattr(message_factory.MessageFactory, "GetPrototype"):
        message_factory.MessageFactory.GetPrototype = lambda self, desc: message_factory.GetMessageClass(desc)
    probe = solution_base.calculator_pb2.CalculatorGraphConfig.DESCRIPTOR.fields_by_name["node"]
    if hasattr(probe, "label"):
        return

    def modify_calculator_options(self, config, calculator_params) -> None:
        nested: dict = {}
        for compound, value in calculator_params.items():
            parts = compound.split(".")
            if len(parts) != 2:
                raise ValueError(f'The key "{compound}" in the calculator_params is invalid.')
            nested.setdefault(parts[0], []).append((parts[1], value))

        def modify(options, fields) -> None:
            for name, value in fields:
                if value is None:
                    options.ClearField(name)
                elif options.DESCRIPTOR.fields_by_name[name].is_repeated:
                    options.ClearField(name)
                    getattr(options, name).extend(value)
                else:
                    setattr(options, name, value)

        modified = 0
        for node in config.node:
            if node.name not in nested:
                continue
            options_type = solution_base.CALCULATOR_TO_OPTIONS.get(node.calculator)
            if options_type is None:
                raise ValueError(f"Modifying the calculator options of {node.name} is not supported.")
            if node.node_options:
                for elem in node.node_options:
                    if elem.type_url.split("/")[-1] == options_type.DESCRIPTOR.full_name:
                        options = options_type.FromString(elem.value)
                        modify(options, nested[node.name])
                        elem.value = options.SerializeToString()
                        break
                else:
                    options = options_type()
                    modify(options, nested[node.name])
                    node.node_options.add().Pack(options)
            else:
                modify(node.options.Extensions[options_type.ext], nested[node.name])
            modified += 1
        if modified < len(nested):
            raise ValueError("Not all calculator params are valid.")

    solution_base.SolutionBase._modify_calculator_options = modify_calculator_options


class MediaPipeDetector:
    """COCO-17 keypoints of the most prominent person, with MediaPipe Pose (complexity 1)."""

    def __init__(self, min_detection_confidence: float = 0.5, min_tracking_confidence: float = 0.5) -> None:
        try:
            from google.protobuf import message_factory

            if not hasattr(message_factory.MessageFactory, "GetPrototype"):  # before mediapipe imports
                message_factory.MessageFactory.GetPrototype = lambda self, desc: message_factory.GetMessageClass(desc)
            import mediapipe as mp
        except ImportError as e:
            raise MissingDependency(
                f"MediaPipe is not installed ({e}); install the example's dependencies:\n    {INSTALL_HINT}"
            ) from None
        if not hasattr(mp, "solutions"):
            raise MissingDependency(
                f"mediapipe {getattr(mp, '__version__', '?')} has no legacy `mediapipe.solutions` (removed after "
                f"0.10.21, whose Pose models ship inside the wheel; later releases need a model file downloaded "
                f"separately). Install 0.10.21:\n    {INSTALL_HINT}"
            )
        from mediapipe.python import solution_base

        _protobuf_compat(solution_base)
        # model_complexity=1: pose_detection.tflite and pose_landmark_full.tflite are in the
        # wheel. (2 would download pose_landmark_heavy.tflite on first use.)
        self._pose = mp.solutions.pose.Pose(
            static_image_mode=False,
            model_complexity=1,
            min_detection_confidence=min_detection_confidence,
            min_tracking_confidence=min_tracking_confidence,
        )

    def __call__(self, rgb: np.ndarray) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """``(keypoints (17, 2) pixels, confidence (17,))`` of an RGB frame, or None."""
        h, w = rgb.shape[:2]
        res = self._pose.process(rgb)
        if res.pose_landmarks is None:
            return None
        lm = res.pose_landmarks.landmark
        sel = [lm[i] for i in COCO_FROM_MEDIAPIPE]
        kp = np.array([[p.x * w, p.y * h] for p in sel], dtype=np.float32)
        conf = np.clip(np.array([p.visibility for p in sel], dtype=np.float32), 0.0, 1.0)
        if not (np.all(np.isfinite(kp)) and np.all(np.isfinite(conf))):
            return None
        return kp, conf

    def close(self) -> None:
        self._pose.close()


@dataclass
class VideoPoses:
    """What :func:`video_to_poses` produced (T = frames with a detection)."""

    keypoints_2d: np.ndarray  # (T, 17, 2) COCO-17 pixels
    confidence: np.ndarray  # (T, 17)
    pose_3d: np.ndarray  # (T, 17, 3) the lifter's poses (metres, Human3.6M order)
    adjusted_3d: np.ndarray  # (T, 17, 3)
    bone_lengths: np.ndarray  # (T, 16)
    video_frame: np.ndarray  # (T,) video frame number of each
    image_size: Tuple[int, int]
    fps: float
    frames_read: int
    lifter: str
    seconds: float
    stats: dict = field(default_factory=dict)
    root_3d: Optional[np.ndarray] = None  # (T, 3) the placed pelvis (camera space, metres), with motion

    def placed_3d(self) -> np.ndarray:
        """The adjusted poses moved to their placed pelvis (as they were without motion)."""
        if self.root_3d is None:
            return self.adjusted_3d
        return self.adjusted_3d + self.root_3d[:, None, :]

    def save(self, path) -> Path:
        """The replay ``.npz`` (``blapose.load_replay`` / ``blapose-client replay`` read it)."""
        out = Path(path)
        np.savez(
            out,
            keypoints_2d=self.keypoints_2d.astype(np.float32),
            pose_3d=self.pose_3d.astype(np.float32),
            image_size=np.array(self.image_size, dtype=np.float32),
            layout=np.array([3], dtype=np.float32),  # COCO-17
            confidence=self.confidence.astype(np.float32),
            fps=np.array([self.fps], dtype=np.float32),
            adjusted_3d=self.adjusted_3d.astype(np.float32),
            bone_lengths=self.bone_lengths.astype(np.float32),
            video_frame=self.video_frame.astype(np.float32),
            **({} if self.root_3d is None else {"root_3d": self.root_3d.astype(np.float32)}),
        )
        return out


def read_frames(path, max_frames: Optional[int] = None):
    """``(rgb frames iterator, (w, h), fps, frame count or 0)`` of a video file."""
    cv2 = _import_cv2()
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise FileNotFoundError(f"cannot open video {path}")
    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    fps = float(cap.get(cv2.CAP_PROP_FPS)) or 0.0
    count = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
    if max_frames is not None:
        count = min(count, max_frames) if count else max_frames

    def frames() -> Iterator[np.ndarray]:
        try:
            n = 0
            while max_frames is None or n < max_frames:
                ok, bgr = cap.read()
                if not ok:
                    break
                n += 1
                yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        finally:
            cap.release()

    return frames(), (w, h), (fps if 0 < fps < 1000 else 25.0), count


def load_lifter(spec: str) -> Lifter:
    """``MODULE:FUNCTION`` (module importable or a ``.py`` path) -> the callable."""
    module, _, name = spec.rpartition(":")
    if not module or not name:
        raise ValueError(f"--lifter wants MODULE:FUNCTION, got {spec!r}")
    if module.endswith(".py"):
        loaded = importlib.util.spec_from_file_location(Path(module).stem, module)
        if loaded is None or loaded.loader is None:
            raise ValueError(f"cannot load {module}")
        mod = importlib.util.module_from_spec(loaded)
        loaded.loader.exec_module(mod)
    else:
        mod = importlib.import_module(module)
    return getattr(mod, name)


def video_to_poses(
    video,
    server: str = "http://127.0.0.1:50051",
    *,
    max_frames: Optional[int] = None,
    lifter: Optional[Lifter] = None,
    model: Optional[str] = None,
    token: Optional[str] = None,
    detector: Optional[Callable[[np.ndarray], Optional[Tuple[np.ndarray, np.ndarray]]]] = None,
    progress: Optional[Callable[[int, int, int, float], None]] = None,
    motion: bool = True,
) -> VideoPoses:
    """Detect, lift and adjust every frame of ``video``; see the module docstring.

    ``motion`` runs the server's causal motion stage at the video's frame rate
    (smoothed directions, the pelvis placed: ``VideoPoses.root_3d``).

    ``lifter=None`` uses the server's lifter (embedded or ``--lifter-weights``); ``detector``
    (default :class:`MediaPipeDetector`) maps an RGB frame to ``(keypoints, confidence)``
    or None; ``progress(frames_read, frame_count_or_0, detections, seconds)`` is called
    after every frame.
    """
    frames, image_size, fps, count = read_frames(video, max_frames)
    own_detector = detector is None
    if detector is None:
        detector = MediaPipeDetector()
    start = time.monotonic()
    sent: List[Tuple[np.ndarray, np.ndarray, int, Optional[np.ndarray]]] = []
    read = 0

    def detections():
        nonlocal read
        for i, rgb in enumerate(frames):
            read = i + 1
            found = detector(rgb)
            if found is not None:
                kp, conf = found
                pose = None
                if lifter is not None:
                    pose = np.asarray(lifter(kp, conf, image_size), dtype=np.float32).reshape(17, 3)
                sent.append((kp, conf, i, pose))
                yield (kp, pose, conf)
            if progress is not None:
                progress(read, count, len(sent), time.monotonic() - start)

    try:
        with blapose.Client(server, token=token) as client:
            if lifter is None and client.info().lifter is None:
                raise blapose.BlaposeError(
                    f"the server at {server} has no lifter (started with --no-lifter): start it "
                    f"without that flag, or pass a lifter (--lifter MODULE:FUNCTION)"
                )
            with client.session(
                layout="coco17", image_size=image_size, model=model, server_lifter=lifter is None, label=str(video),
                motion=fps if motion else None,
            ) as s:  # fmt: skip
                results = list(s.stream(detections()))
                lifter_name = s.info.lifter or f"client: {getattr(lifter, '__name__', 'lifter')}"
    finally:
        if own_detector:
            detector.close()  # type: ignore[union-attr]
    seconds = time.monotonic() - start

    keep = []
    for k, r in enumerate(results):
        lifted = sent[k][3] if lifter is not None else r.lifted
        placed = not motion or r.root is not None
        if placed and lifted is not None and np.all(np.isfinite(r.adjusted)) and np.all(np.isfinite(lifted)):
            keep.append((k, lifted))
    # Frames dropped here: answers lost to a dropped connection and rebuilt locally
    # without the server's lifted pose or the motion stage (see python/README.md); rare.
    n = len(keep)

    def stack(values, shape):
        return np.stack(values).astype(np.float32) if n else np.zeros((0, *shape), np.float32)

    return VideoPoses(
        keypoints_2d=stack([sent[k][0] for k, _ in keep], (17, 2)),
        confidence=stack([sent[k][1] for k, _ in keep], (17,)),
        pose_3d=stack([p for _, p in keep], (17, 3)),
        adjusted_3d=stack([results[k].adjusted for k, _ in keep], (17, 3)),
        bone_lengths=stack([results[k].bone_lengths for k, _ in keep], (16,)),
        video_frame=np.array([sent[k][2] for k, _ in keep], dtype=np.int64),
        image_size=image_size,
        fps=fps,
        frames_read=read,
        lifter=lifter_name,
        seconds=seconds,
        stats={"detections": len(sent), "answered": len(results), "kept": n},
        root_3d=stack([results[k].root for k, _ in keep], (3,)) if motion else None,
    )


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("video", help="any video OpenCV reads (mp4, avi, ...)")
    ap.add_argument("--server", default="http://127.0.0.1:50051", help="blapose server URL")
    ap.add_argument("--token", default=None, help="the server's --auth-token, if any")
    ap.add_argument("--out", default="poses.npz", help="replay .npz to write")
    ap.add_argument("--html", default=None, help="HTML report to write (lifted vs adjusted)")
    ap.add_argument("--bvh", default=None, help="BVH to write (Blender, animation tools): the adjusted motion")
    ap.add_argument("--c3d", default=None, help="C3D to write (biomechanics tools): the adjusted joints as markers")
    ap.add_argument("--max-frames", type=int, default=None, help="stop after this many video frames")
    ap.add_argument("--model", default=None, help="session model (default: the server's streaming default)")
    ap.add_argument(
        "--lifter",
        default=None,
        metavar="MODULE:FUNCTION",
        help="lift here with f(keypoints (17,2), confidence (17,), image_size) -> (17,3) metres, "
        "Human3.6M order, instead of the server's lifter",
    )
    ap.add_argument(
        "--no-motion",
        action="store_true",
        help="no motion stage: the lifter's directions as they are, every pose around its own pelvis",
    )
    ap.add_argument("--quiet", action="store_true", help="no progress line")
    args = ap.parse_args(argv)

    if not Path(args.video).is_file():
        print(f"error: no such video file: {args.video}", file=sys.stderr)
        return 2
    for path in (args.out, args.html, args.bvh, args.c3d):
        if path and not Path(path).resolve().parent.is_dir():
            print(f"error: cannot write {path}: its directory does not exist", file=sys.stderr)
            return 2
    tty = sys.stderr.isatty()

    def progress(read: int, count: int, found: int, secs: float) -> None:
        if args.quiet or (not tty and read % 50):
            return
        total = f"/{count}" if count else ""
        rate = read / secs if secs > 0 else 0.0
        print(f"\rframe {read}{total}  detections {found}  {rate:.1f} fps", end="" if tty else "\n",
              file=sys.stderr, flush=True)  # fmt: skip

    try:
        lifter = load_lifter(args.lifter) if args.lifter else None
        res = video_to_poses(args.video, args.server, max_frames=args.max_frames, lifter=lifter, model=args.model,
                             token=args.token, progress=progress, motion=not args.no_motion)  # fmt: skip
    except MissingDependency as e:
        print(f"\nerror: {e}", file=sys.stderr)
        return 3
    except (blapose.BlaposeError, FileNotFoundError, ValueError) as e:
        print(f"\nerror: {e}", file=sys.stderr)
        return 1
    if tty and not args.quiet:
        print(file=sys.stderr)
    if res.stats["kept"] == 0:
        print(f"error: no person detected in {res.frames_read} frames; nothing written", file=sys.stderr)
        return 1
    res.save(args.out)
    if args.html:
        blapose.write_html(
            args.html, res.pose_3d, res.adjusted_3d, fps=res.fps, title=Path(args.video).name,
            before_label=f"lifted ({res.lifter})", after_label="adjusted",
            # the page shows the frame count itself ("frames: T"); the video's count is another
            info={"lifter": res.lifter, "detector": "mediapipe pose (complexity 1)",
                  "video": f"{res.frames_read} frames read, {res.stats['kept']} with a person",
                  **({} if res.root_3d is None else {"motion": "pelvis placed, focal length assumed from the image"})},
            root=res.root_3d,
        )  # fmt: skip
    exported = []
    # A stream's lengths change as its estimate converges; a skeleton's cannot, so the
    # files re-pose every frame with the final lengths (blapose.export).
    try:
        if args.bvh:
            report = blapose.write_bvh(args.bvh, res.placed_3d(), res.bone_lengths[-1], fps=res.fps)
            exported.append(f"{args.bvh} (largest frame-to-frame joint rotation {report.max_step_deg:.1f} deg)")
        if args.c3d:
            blapose.write_c3d(args.c3d, res.placed_3d(), res.bone_lengths[-1], fps=res.fps)
            exported.append(args.c3d)
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    fps = res.frames_read / res.seconds if res.seconds > 0 else 0.0
    lengths = res.bone_lengths[-1]
    travel = float(np.linalg.norm(np.diff(res.root_3d, axis=0), axis=1).sum()) if res.root_3d is not None else 0.0
    print(
        f"{res.frames_read} frames read, {res.stats['detections']} with a person, {res.stats['kept']} adjusted "
        f"(lifter {res.lifter}) in {res.seconds:.1f} s: {fps:.1f} frames/s, "
        f"{1000 * res.seconds / max(res.frames_read, 1):.0f} ms/frame\n"
        "final bone lengths (m): " + " ".join(f"{n}={v:.3f}" for n, v in zip(blapose.BONE_NAMES, lengths)) + "\n"
        f"wrote {args.out}" + (f" and {args.html}" if args.html else "")
        + (f"\nexported {', '.join(exported)}: every frame re-posed with the final bone lengths" if exported else "")
        + (f"\nmotion: the pelvis travelled {travel:.2f} m (focal length assumed from the image size)"
           if res.root_3d is not None else "")
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
