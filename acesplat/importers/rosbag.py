"""Import a ROS 2 bag (rosbag2: sqlite3 or MCAP storage) into the ACE layout, read with ``rosbags`` (no ROS install).

What is read:
- images: ``sensor_msgs/msg/Image`` (rgb8, bgr8, rgba8, bgra8, mono8) or ``sensor_msgs/msg/CompressedImage``
  (jpeg, png); each image's time is its ``header.stamp`` (the bag's receive time if the stamp is zero);
- intrinsics: ``sensor_msgs/msg/CameraInfo`` (``--camera-info-topic``; default ``camera_info`` beside the image topic).
  ROS's K already follows OpenCV's pixel convention. ``plumb_bob`` and ``rational_polynomial`` distortion is undone
  with OpenCV on import and the undistorted K is written; other models are refused. An image topic named
  ``image_rect*`` is already rectified: its K is the projection matrix's left 3x3 and nothing is undistorted;
- poses, one of: a ``geometry_msgs/msg/PoseStamped``, ``PoseWithCovarianceStamped`` or ``nav_msgs/msg/Odometry`` topic
  (the pose of a frame in ``header.frame_id``), or TF (``--tf PARENT:CHILD``: ``/tf`` and ``/tf_static`` chained from
  PARENT to CHILD through any intermediate frames, each edge interpolated on its own).

Poses are interpolated to each image stamp (centres linearly, rotations by slerp) when samples on both sides lie within
``pose_tolerance`` seconds of it; other images are skipped and counted in the summary.

Axes: our pose is camera-to-world with OpenCV camera axes (x right, y down, z forward). A ROS ``*_optical_frame``
already has those axes. A body or ``camera_link`` frame has REP-103 axes (x forward, y left, z up) and is turned by
the fixed rotation ``BODY_TO_OPTICAL``. ``optical=None`` (the default) decides from the child frame's name (TF and
Odometry: optical when it ends in ``optical_frame``, body otherwise); a PoseStamped names no child frame, so it needs
``optical=True`` or ``False``. World axes are the bag's (REP-103: z up), in metres.

Selection and split: posed images in time order, every ``every``-th one, then (``min_baseline`` > 0) only those whose
centre moved at least that far from the last kept one. The test split is held out by time: the span is cut into
blocks of ``test_block`` seconds from the first kept image, and of every ``test_every`` consecutive blocks the last
goes to test (blocks k-1, 2k-1, ... for k = ``test_every``); ``test_every=0`` puts every frame in train. Whole blocks
keep test views away from the training views next to them in time, and spread the test set over the trajectory.
"""

from __future__ import annotations

import math
import re
import shutil
import sqlite3
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from acesplat.core.config import knob
from acesplat.core.errors import InputError
from acesplat.core.geometry import interpolate_pose, invert_pose, make_pose, quat_to_matrix
from acesplat.importers.common import (
    CameraSpec,
    ImportSummary,
    Progress,
    SourceFrame,
    check_output,
    check_test_every,
    default_test_every,
    write_scene,
)

BODY_TO_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
"""Pose of an optical frame in its REP-103 body frame (optical x = -body y, y = -body z, z = body x): the usual
``camera_link -> camera_optical_frame`` static transform (roll -90 deg, yaw -90 deg)."""

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
)
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
TF_TOPICS = ("/tf", "/tf_static")
RAW_ENCODINGS = {  # encoding -> (channels, cv2 conversion to BGR or None)
    "rgb8": (3, cv2.COLOR_RGB2BGR),
    "bgr8": (3, None),
    "rgba8": (4, cv2.COLOR_RGBA2BGR),
    "bgra8": (4, cv2.COLOR_BGRA2BGR),
    "mono8": (1, cv2.COLOR_GRAY2BGR),
    "8UC1": (1, cv2.COLOR_GRAY2BGR),
    "8UC3": (3, None),
}
UNDISTORTED_MODELS = {"plumb_bob": (4, 5), "rational_polynomial": (8,)}
"""Distortion models OpenCV undoes with ROS's coefficient order, and the coefficient counts accepted."""
NO_DISTORTION_MODELS = ("", "none")
BAG_SUFFIXES = (".mcap", ".db3")


@dataclass
class RosbagImportConfig:
    """What to read from a ROS 2 bag and which frames to keep (see the module docstring)."""

    image_topic: str | None = knob(None, "ROS bag: image topic (sensor_msgs/Image or CompressedImage).")
    pose_topic: str | None = knob(None, "ROS bag: pose topic (PoseStamped, PoseWithCovarianceStamped or Odometry).")
    tf: str | None = knob(None, "ROS bag: PARENT:CHILD frames to chain through /tf and /tf_static (instead of poses).")
    camera_info_topic: str | None = knob(
        None, "ROS bag: CameraInfo topic (default: camera_info beside the image topic)."
    )
    optical: bool | None = knob(
        None, "ROS bag: the pose is of an optical frame (OpenCV axes) or a REP-103 body frame; default from its name."
    )
    every: int = knob(1, "ROS bag: keep every N-th posed image (in time order).")
    min_baseline: float = knob(0.0, "ROS bag: keep an image only if it moved this many metres from the last kept one.")
    pose_tolerance: float = knob(0.1, "ROS bag: seconds a pose sample may lie from an image stamp, on each side.")
    test_block: float = knob(10.0, "ROS bag: test split by time: blocks of this many seconds, every test_every-th.")


@dataclass
class RosbagSummary(ImportSummary):
    """An import summary with what the bag reader dropped."""

    images: int = 0
    """Image messages on the topic."""
    skipped_no_pose: int = 0
    """Images with no pose sample within the tolerance on both sides."""
    dropped_by_selection: int = 0
    """Posed images left out by ``every`` / ``min_baseline``."""
    pose_source: str = ""
    optical: bool = True


def _stamp_ns(header: Any, fallback: int) -> int:
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns if ns > 0 else int(fallback)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


def _seconds(ns: int) -> str:
    return f"{ns / 1e9:.3f} s"


class Track:
    """Poses (N, 4, 4) of one frame at sorted times (ns), or one constant pose (a static transform)."""

    def __init__(self, stamps: list[int], poses: list[np.ndarray], static: bool = False) -> None:
        order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
        self.stamps = np.asarray(stamps, dtype=np.int64)[order]
        self.poses = np.stack(poses)[order] if poses else np.zeros((0, 4, 4))
        self.static = static

    def at(self, t: int, tol_ns: int) -> np.ndarray | None:
        """The pose at time ``t`` (ns), interpolated between the samples around it; None outside the tolerance."""
        if self.static:
            return self.poses[-1]
        i = int(np.searchsorted(self.stamps, t, side="left"))
        if i < len(self.stamps) and self.stamps[i] == t:
            return self.poses[i]
        if i == 0 or i == len(self.stamps):
            return None
        t0, t1 = int(self.stamps[i - 1]), int(self.stamps[i])
        if t - t0 > tol_ns or t1 - t > tol_ns:
            return None
        return interpolate_pose(self.poses[i - 1], self.poses[i], (t - t0) / (t1 - t0))

    def span(self) -> tuple[int, int]:
        return int(self.stamps[0]), int(self.stamps[-1])


def _transform(translation: Any, rotation: Any, where: str, bag: Path) -> np.ndarray:
    """4x4 from a ROS translation (x, y, z) and quaternion (x, y, z, w)."""
    q = np.array([rotation.w, rotation.x, rotation.y, rotation.z], dtype=np.float64)
    t = np.array([translation.x, translation.y, translation.z], dtype=np.float64)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise InputError(bag, f"{where}: non-finite pose")
    if np.linalg.norm(q) < 1e-8:
        raise InputError(bag, f"{where}: quaternion is zero")
    return make_pose(quat_to_matrix(q), t)


def _frame_id(name: str) -> str:
    return name.strip().lstrip("/")


def is_optical_frame(name: str) -> bool:
    """True for a ROS optical frame name (``camera_color_optical_frame``), whose axes are OpenCV's."""
    return _frame_id(name).endswith("optical_frame")


class TfChain:
    """PARENT -> CHILD through the TF tree: each edge a ``Track``, composed at the requested time."""

    def __init__(self, edges: dict[tuple[str, str], Track], parent: str, child: str, bag: Path) -> None:
        up: dict[str, str] = {}
        for p, c in edges:
            if c in up and up[c] != p:
                raise InputError(bag, f"TF frame {c!r} has two parents ({up[c]!r} and {p!r})")
            up[c] = p
        frames = sorted(set(up) | set(up.values()))
        for name in (parent, child):
            if name not in frames:
                raise InputError(bag, f"TF has no frame {name!r}; frames: {', '.join(frames) or 'none'}")

        def to_root(f: str) -> list[str]:
            chain = [f]
            while chain[-1] in up and len(chain) <= len(up):
                chain.append(up[chain[-1]])
            return chain

        from_child, from_parent = to_root(child), to_root(parent)
        common = next((f for f in from_child if f in from_parent), None)
        if common is None:
            raise InputError(bag, f"TF frames {parent!r} and {child!r} are not connected (no common ancestor)")
        # Edges (parent, child) from the common ancestor down to each end.
        self.down_child = [(up[f], f) for f in reversed(from_child[: from_child.index(common)])]
        self.down_parent = [(up[f], f) for f in reversed(from_parent[: from_parent.index(common)])]
        self.edges = edges
        dynamic = [edges[e] for e in self.down_child + self.down_parent if not edges[e].static]
        self.dynamic = dynamic
        self.path = " -> ".join(list(reversed(from_parent[: from_parent.index(common) + 1])) + from_child[::-1][1:])

    def _compose(self, path: list[tuple[str, str]], t: int, tol_ns: int) -> np.ndarray | None:
        T = np.eye(4)
        for e in path:
            step = self.edges[e].at(t, tol_ns)
            if step is None:
                return None
            T = T @ step
        return T

    def at(self, t: int, tol_ns: int) -> np.ndarray | None:
        a = self._compose(self.down_parent, t, tol_ns)
        b = self._compose(self.down_child, t, tol_ns)
        return None if a is None or b is None else invert_pose(a) @ b

    def span(self) -> tuple[int, int] | None:
        if not self.dynamic:
            return None
        return max(tr.span()[0] for tr in self.dynamic), min(tr.span()[1] for tr in self.dynamic)


def _rosbags() -> tuple[Any, Any, tuple[type[BaseException], ...]]:
    """rosbags' Reader, the ROS 2 typestore, and the errors a damaged bag raises (imported on use: an extra)."""
    try:
        from rosbags.rosbag2 import Reader, ReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise InputError(None, "reading ROS 2 bags needs rosbags: pip install 'acesplat-edge[ros]'") from None
    errors: tuple[type[BaseException], ...] = (ReaderError, OSError, sqlite3.Error, struct.error, EOFError)
    try:
        import apsw

        errors += (apsw.Error,)
    except ImportError:
        pass
    return Reader, get_typestore(Stores.ROS2_HUMBLE), errors


def find_bag(src: str | Path) -> Path:
    """The path rosbags opens: a folder with metadata.yaml, or one .mcap/.db3 file (given or alone in a folder)."""
    src = Path(src)
    if not src.exists():
        raise InputError(src, "source does not exist")
    if src.is_file():
        if src.name == "metadata.yaml":
            return src.parent
        if src.suffix.lower() in BAG_SUFFIXES:
            return src
        raise InputError(src, "not a ROS 2 bag (expected a folder with metadata.yaml, or a .mcap / .db3 file)")
    if (src / "metadata.yaml").is_file():
        return src
    files = sorted(p for p in src.iterdir() if p.suffix.lower() in BAG_SUFFIXES)
    if len(files) == 1:
        return files[0]
    if files:
        raise InputError(src, f"{len(files)} bag files and no metadata.yaml: pass one of them")
    raise InputError(src, "not a ROS 2 bag (no metadata.yaml, .mcap or .db3 file)")


def _topics_text(connections: list[Any], types: tuple[str, ...] | None = None) -> str:
    rows = sorted({(c.topic, c.msgtype) for c in connections if types is None or c.msgtype in types})
    return ", ".join(f"{t} ({m})" for t, m in rows) or "none"


def _check_config(config: RosbagImportConfig) -> None:
    if config.every < 1 or isinstance(config.every, bool):
        raise InputError(None, f"every must be an integer >= 1, got {config.every!r}")
    if not (math.isfinite(config.min_baseline) and config.min_baseline >= 0):
        raise InputError(None, f"min_baseline must be >= 0 metres, got {config.min_baseline!r}")
    if not (math.isfinite(config.pose_tolerance) and config.pose_tolerance > 0):
        raise InputError(None, f"pose_tolerance must be > 0 seconds, got {config.pose_tolerance!r}")
    if not (math.isfinite(config.test_block) and config.test_block > 0):
        raise InputError(None, f"test_block must be > 0 seconds, got {config.test_block!r}")
    if (config.pose_topic is None) == (config.tf is None):
        raise InputError(None, "give exactly one pose source: a pose topic or TF frames PARENT:CHILD")
    if config.tf is not None and not re.fullmatch(r"[^:\s]+:[^:\s]+", config.tf.strip()):
        raise InputError(
            None, f"TF frames must look like PARENT:CHILD (e.g. map:camera_optical_frame), got {config.tf!r}"
        )


@dataclass
class _Camera:
    spec: CameraSpec
    note: str


def _camera_from_info(msg: Any, bag: Path, topic: str, rectified: bool) -> _Camera:
    where = f"{topic} ({CAMERA_INFO_TYPE})"
    w, h = int(msg.width), int(msg.height)
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    P = np.asarray(msg.p, dtype=np.float64).reshape(3, 4)
    if rectified:
        K = P[:, :3]
    if w <= 0 or h <= 0:
        raise InputError(bag, f"{where}: image size must be positive, got {w}x{h}")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(bag, f"{where}: {'P' if rectified else 'K'} needs finite positive focal lengths, got {K[:2]}")
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1 or int(msg.roi.width) or int(msg.roi.height):
        raise InputError(bag, f"{where}: binning / region of interest are not supported")
    model = str(msg.distortion_model).strip()
    D = tuple(float(v) for v in msg.d)
    dist: tuple[float, ...] = ()
    if rectified:
        note = f"{topic}: image topic is rectified; K from P, no undistortion"
    elif model in UNDISTORTED_MODELS:
        if len(D) not in UNDISTORTED_MODELS[model]:
            raise InputError(bag, f"{where}: {model} needs {UNDISTORTED_MODELS[model]} coefficients, got {len(D)}")
        if not all(math.isfinite(v) for v in D):
            raise InputError(bag, f"{where}: distortion coefficients are not finite")
        dist = D if any(D) else ()
        note = f"{topic}: {model} distortion" + (" undone with OpenCV" if dist else " (all zero)")
    elif model.lower() in NO_DISTORTION_MODELS and not any(D):
        note = f"{topic}: no distortion"
    else:
        raise InputError(
            bag,
            f"{where}: distortion model {model!r} is not supported (only {', '.join(UNDISTORTED_MODELS)}); "
            "record the rectified image topic (image_rect) instead",
        )
    # CameraSpec holds the pixel-corner convention; ROS's K has OpenCV's (pixel centre at 0).
    spec = CameraSpec(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + 0.5, cy=K[1, 2] + 0.5, width=w, height=h, dist=dist)
    return _Camera(spec, note)


def _camera_key(msg: Any) -> tuple:
    return (
        int(msg.width), int(msg.height), str(msg.distortion_model),
        tuple(np.asarray(msg.k).tolist()), tuple(np.asarray(msg.d).tolist()), tuple(np.asarray(msg.p).tolist()),
    )  # fmt: skip


def decode_image(msg: Any, msgtype: str) -> np.ndarray:
    """BGR uint8 (H, W, 3) of an Image or CompressedImage message; ValueError saying why not."""
    if msgtype == "sensor_msgs/msg/CompressedImage":
        fmt = str(msg.format).lower()
        if "compresseddepth" in fmt:
            raise ValueError(f"compressed depth ({msg.format!r}) is not a colour image")
        data = np.asarray(msg.data, dtype=np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
        if img is None:
            raise ValueError(f"cannot decode the compressed image (format {msg.format!r})")
        return img
    enc = str(msg.encoding)
    if enc not in RAW_ENCODINGS:
        raise ValueError(f"image encoding {enc!r} is not supported (supported: {', '.join(RAW_ENCODINGS)})")
    ch, conversion = RAW_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if h <= 0 or w <= 0 or step < w * ch or data.size < step * h:
        raise ValueError(f"{w}x{h} {enc} image with step {step} does not fit its {data.size} bytes")
    img = data[: step * h].reshape(h, step)[:, : w * ch].reshape(h, w, ch)
    return np.ascontiguousarray(img if conversion is None else cv2.cvtColor(img, conversion))


def _select(poses: list[np.ndarray], every: int, min_baseline: float) -> list[int]:
    """Indices of ``poses`` (time order) kept by every-N-th, then by the minimum baseline from the last kept centre."""
    kept: list[int] = []
    for i in range(0, len(poses), every):
        if min_baseline > 0 and kept and np.linalg.norm(poses[i][:3, 3] - poses[kept[-1]][:3, 3]) < min_baseline:
            continue
        kept.append(i)
    return kept


def time_block_split(stamps: list[int], block_s: float, test_every: int) -> list[bool]:
    """For each stamp (ns, sorted), whether it goes to test: blocks of ``block_s`` seconds from the first stamp, the
    last of every ``test_every`` consecutive blocks held out (none for ``test_every=0``)."""
    if test_every == 0 or not stamps:
        return [False] * len(stamps)
    block_ns = block_s * 1e9
    return [int((t - stamps[0]) // block_ns) % test_every == test_every - 1 for t in stamps]


def import_rosbag(
    src: str | Path,
    out_scene: str | Path,
    config: RosbagImportConfig | None = None,
    test_every: int = default_test_every(),
    image_ext: str = ".png",
    progress: Progress | None = None,
) -> RosbagSummary:
    """Write the ACE layout at ``out_scene`` from the ROS 2 bag ``src`` (folder, metadata.yaml, .mcap or .db3).

    Reads the bag twice: poses, TF, CameraInfo and image stamps first; then only the kept images, decoded into a
    temporary folder beside ``out_scene`` and written by the common writer (all or nothing).
    """
    config = config or RosbagImportConfig()
    test_every = check_test_every(test_every)
    _check_config(config)
    check_output(out_scene)
    bag = find_bag(src)
    Reader, typestore, BAG_ERRORS = _rosbags()
    try:
        with Reader(bag) as reader:
            return _import(reader, typestore, bag, Path(out_scene), config, test_every, image_ext, progress)
    except BAG_ERRORS as e:  # a bag rosbags cannot open, a corrupt database or chunk
        raise InputError(bag, f"cannot read the bag ({type(e).__name__}: {_one_line(e)})") from None


def _import(
    reader: Any,
    typestore: Any,
    bag: Path,
    out_scene: Path,
    config: RosbagImportConfig,
    test_every: int,
    image_ext: str,
    progress: Progress | None,
) -> RosbagSummary:
    connections = list(reader.connections)
    by_topic: dict[str, list[Any]] = {}
    for c in connections:
        by_topic.setdefault(c.topic, []).append(c)

    def topic(name: str | None, types: tuple[str, ...], what: str) -> list[Any]:
        if not name:
            raise InputError(
                bag, f"no {what} topic given; {what} topics in the bag: {_topics_text(connections, types)}"
            )
        conns = by_topic.get(name, [])
        if not conns:
            raise InputError(bag, f"no topic {name!r} in the bag; topics: {_topics_text(connections)}")
        bad = sorted({c.msgtype for c in conns if c.msgtype not in types})
        if bad:
            raise InputError(bag, f"topic {name!r} is {', '.join(bad)}, not a {what} topic ({', '.join(types)})")
        return conns

    def deserialize(raw: bytes, c: Any, index: int) -> Any:
        try:
            return typestore.deserialize_cdr(raw, c.msgtype)
        except Exception as e:
            raise InputError(
                bag, f"{c.topic} message {index}: cannot deserialize {c.msgtype} ({_one_line(e)})"
            ) from None

    image_conns = topic(config.image_topic, IMAGE_TYPES, "image")
    image_topic = str(config.image_topic)
    rectified = image_topic.rstrip("/").rsplit("/", 1)[-1].startswith("image_rect")
    info_name = config.camera_info_topic
    if info_name is None:
        info_name = image_topic.rstrip("/").rsplit("/", 1)[0] + "/camera_info"
        if info_name not in by_topic:
            raise InputError(
                bag,
                f"no CameraInfo topic {info_name!r} beside {image_topic!r}; give one "
                f"(CameraInfo topics: {_topics_text(connections, (CAMERA_INFO_TYPE,))})",
            )
    info_conns = topic(info_name, (CAMERA_INFO_TYPE,), "CameraInfo")

    pose_conns: list[Any] = []
    if config.pose_topic is not None:
        pose_conns = topic(config.pose_topic, POSE_TYPES, "pose")
        if config.optical is None and any(c.msgtype != "nav_msgs/msg/Odometry" for c in pose_conns):
            raise InputError(
                bag,
                f"{config.pose_topic}: the pose names no child frame; say whether it is of an optical frame "
                "(OpenCV axes: --optical) or a REP-103 body frame (x forward, z up: --body)",
            )
        tf_parent = tf_child = ""
    else:
        tf_parent, tf_child = (_frame_id(s) for s in str(config.tf).split(":"))
        pose_conns = [c for c in connections if c.topic in TF_TOPICS and c.msgtype == TF_TYPE]
        if not pose_conns:
            raise InputError(bag, f"no /tf or /tf_static ({TF_TYPE}) in the bag; topics: {_topics_text(connections)}")

    # ---- pass 1: poses, TF, camera info, image stamps
    stamps: list[int] = []
    camera: _Camera | None = None
    camera_key: tuple | None = None
    pose_stamps: list[int] = []
    pose_list: list[np.ndarray] = []
    child_names: set[str] = set()
    tf_edges: dict[tuple[str, str], tuple[list[int], list[np.ndarray]]] = {}
    tf_static: dict[tuple[str, str], np.ndarray] = {}
    counts: dict[str, int] = {}
    image_ids = {c.id for c in image_conns}
    info_ids = {c.id for c in info_conns}
    for c, t_bag, raw in reader.messages(connections=image_conns + info_conns + pose_conns):
        index = counts[c.topic] = counts.get(c.topic, -1) + 1
        if c.id in image_ids:
            msg = deserialize(raw, c, index)
            stamps.append(_stamp_ns(msg.header, t_bag))
        elif c.id in info_ids:
            msg = deserialize(raw, c, index)
            key = _camera_key(msg)
            if camera is None:
                camera, camera_key = _camera_from_info(msg, bag, c.topic, rectified), key
            elif key != camera_key:
                raise InputError(bag, f"{c.topic} message {index}: camera calibration changes during the bag")
        elif c.msgtype == TF_TYPE:
            msg = deserialize(raw, c, index)
            for k, tr in enumerate(msg.transforms):
                edge = (_frame_id(tr.header.frame_id), _frame_id(tr.child_frame_id))
                T = _transform(tr.transform.translation, tr.transform.rotation, f"{c.topic} message {index}[{k}]", bag)
                if c.topic == "/tf_static":
                    tf_static[edge] = T
                else:
                    series = tf_edges.setdefault(edge, ([], []))
                    series[0].append(_stamp_ns(tr.header, t_bag))
                    series[1].append(T)
        else:
            msg = deserialize(raw, c, index)
            pose = msg.pose.pose if c.msgtype != "geometry_msgs/msg/PoseStamped" else msg.pose
            pose_stamps.append(_stamp_ns(msg.header, t_bag))
            pose_list.append(_transform(pose.position, pose.orientation, f"{c.topic} message {index}", bag))
            if c.msgtype == "nav_msgs/msg/Odometry":
                child_names.add(_frame_id(msg.child_frame_id))
    if not stamps:
        raise InputError(bag, f"topic {image_topic!r} has no messages")
    if camera is None:
        raise InputError(bag, f"topic {info_name!r} has no messages")

    # ---- the pose source and its axes
    source: Track | TfChain
    if config.pose_topic is not None:
        if not pose_list:
            raise InputError(bag, f"topic {config.pose_topic!r} has no messages")
        source = Track(pose_stamps, pose_list)
        child = next(iter(child_names)) if len(child_names) == 1 else ""
        pose_source = f"{config.pose_topic}" + (f" (child frame {child})" if child else "")
        if config.optical is None and not child:
            raise InputError(bag, f"{config.pose_topic}: Odometry messages disagree on the child frame: {child_names}")
    else:
        edges = {e: Track(s, p) for e, (s, p) in tf_edges.items()}
        edges.update({e: Track([0], [T], static=True) for e, T in tf_static.items()})
        source = TfChain(edges, tf_parent, tf_child, bag)
        child = tf_child
        pose_source = f"TF {source.path}"
    optical = config.optical if config.optical is not None else is_optical_frame(child)
    axes = np.eye(4) if optical else BODY_TO_OPTICAL

    # ---- poses at the image stamps, selection, split
    order = sorted(range(len(stamps)), key=lambda i: stamps[i])
    tol_ns = int(round(config.pose_tolerance * 1e9))
    posed: list[int] = []
    posed_poses: list[np.ndarray] = []
    for i in order:
        T = source.at(stamps[i], tol_ns)
        if T is not None:
            posed.append(i)
            posed_poses.append(T @ axes)
    if not posed:
        span = source.span()
        covers = f"covers {_seconds(span[0])} .. {_seconds(span[1])}" if span else "has no samples"
        raise InputError(
            bag,
            f"{pose_source} {covers} but the images span {_seconds(min(stamps))} .. {_seconds(max(stamps))}: "
            f"no image has pose samples within {config.pose_tolerance} s on both sides",
        )
    kept = _select(posed_poses, config.every, config.min_baseline)
    kept_msgs = [posed[k] for k in kept]
    kept_poses = [posed_poses[k] for k in kept]
    kept_stamps = [stamps[i] for i in kept_msgs]
    is_test = time_block_split(kept_stamps, config.test_block, test_every)

    summary = RosbagSummary(
        source=str(bag),
        format="rosbag",
        scene=str(out_scene),
        images=len(stamps),
        skipped_no_pose=len(stamps) - len(posed),
        dropped_by_selection=len(posed) - len(kept),
        pose_source=pose_source,
        optical=bool(optical),
    )
    summary.notes.append(f"poses from {pose_source}, {'optical' if optical else 'REP-103 body'} axes")
    summary.notes.append(camera.note)
    if summary.skipped_no_pose:
        summary.notes.append(
            f"skipped {summary.skipped_no_pose} of {len(stamps)} images: no pose within {config.pose_tolerance} s"
        )
    if summary.dropped_by_selection:
        summary.notes.append(
            f"kept {len(kept)} of {len(posed)} posed images (every {config.every}, "
            f"min baseline {config.min_baseline} m)"
        )
    if test_every and not any(is_test):
        summary.notes.append(f"no test frames: the images span less than {test_every} blocks of {config.test_block} s")

    # ---- pass 2: decode the kept images into a staging folder, then the common writer
    wanted = {m: k for k, m in enumerate(kept_msgs)}
    out_scene.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_scene.name}.bag.", dir=out_scene.parent))
    try:
        frames: list[SourceFrame | None] = [None] * len(kept_msgs)
        index = -1
        for c, _, raw in reader.messages(connections=image_conns):
            index += 1
            if index not in wanted:
                continue
            msg = deserialize(raw, c, index)
            try:
                bgr = decode_image(msg, c.msgtype)
            except ValueError as e:
                raise InputError(bag, f"{c.topic} message {index}: {e}") from None
            k = wanted[index]
            path = staging / f"{k:06d}.bmp"
            if not cv2.imwrite(str(path), bgr):
                raise InputError(path, "cannot write a staged image")
            sec, nsec = divmod(kept_stamps[k], 1_000_000_000)
            frames[k] = SourceFrame(
                name=f"t{sec}_{nsec:09d}",
                image_path=path,
                pose=kept_poses[k],
                camera=camera.spec,
                where=f"{bag} {c.topic} message {index}",
                test=is_test[k],
            )
        if any(f is None for f in frames):
            raise InputError(bag, f"{image_topic}: fewer messages on the second read (bag changed while reading?)")
        write_scene(
            [f for f in frames if f is not None], out_scene, summary, test_every, image_ext=image_ext, progress=progress
        )
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    if test_every:
        k = test_every
        summary.split_rule = (
            f"by time: blocks of {config.test_block} s from the first image, the last of every {k} to test "
            f"(blocks {k - 1}, {2 * k - 1}, ...)"
        )
    else:
        summary.split_rule = "all frames to train (test_every=0)"
    return summary
