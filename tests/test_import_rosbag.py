"""ROS 2 bags written here with rosbags (both storage formats) from a tiny analytic scene import to that scene.

The bag's poses sit 20 ms either side of each image stamp, turned and shifted symmetrically about the true pose, so
interpolation (linear centre, slerp rotation) lands on the original exactly: matching poses prove the interpolation,
the TF chaining and the axis conventions together.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")

from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from acesplat.apps.cli import app  # noqa: E402
from acesplat.core.errors import InputError  # noqa: E402
from acesplat.core.geometry import invert_pose, make_pose, matrix_to_quat, pose_error  # noqa: E402
from acesplat.core.scene import read_split  # noqa: E402
from acesplat.importers import detect_format, import_scene  # noqa: E402
from acesplat.importers.common import Undistorter  # noqa: E402
from acesplat.importers.rosbag import BODY_TO_OPTICAL, RosbagImportConfig, import_rosbag  # noqa: E402
from tests.test_edge_scene import make_room_scene  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
T0 = 1_700_000_000 * 10**9
DT = 100_000_000  # 10 Hz images
HALF = 20_000_000  # pose samples 20 ms before and after each image
IMAGE_TOPIC = "/camera/image_raw"
INFO_TOPIC = "/camera/camera_info"
STATIC_MAP_ODOM = make_pose(cv2.Rodrigues(np.array([0.0, 0.0, 0.3]))[0], [1.0, -2.0, 0.5])
STATIC_BASE_CAM = make_pose(cv2.Rodrigues(np.array([0.0, 0.1, 0.0]))[0], [0.2, 0.0, 0.4])


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> dict:
    root = make_room_scene(tmp_path_factory.mktemp("room") / "room", train=12, test=0)
    split = read_split(root, "train")
    return {"frames": split.frames, "poses": split.poses, "rgb": [f.load_rgb() for f in split.frames]}


def header(ns: int, frame_id: str = "camera_optical_frame"):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                    frame_id=frame_id)  # fmt: skip


def ros_pose(M: np.ndarray):
    q = matrix_to_quat(M[:3, :3])
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0]),
    )


def tf_stamped(ns: int, parent: str, child: str, M: np.ndarray):
    p = ros_pose(M)
    tr = T["geometry_msgs/msg/Transform"](
        translation=T["geometry_msgs/msg/Vector3"](x=p.position.x, y=p.position.y, z=p.position.z),
        rotation=p.orientation,
    )
    return T["geometry_msgs/msg/TransformStamped"](header=header(ns, parent), child_frame_id=child, transform=tr)


def wiggle(M: np.ndarray, sign: int, i: int) -> np.ndarray:
    """``M`` turned about a body axis and shifted, by +- the same amount: the midpoint of the two is ``M``."""
    R = cv2.Rodrigues(sign * np.array([0.02, -0.03 * (i % 3), 0.05]))[0]
    return make_pose(M[:3, :3] @ R, M[:3, 3] + sign * np.array([0.01, 0.004 * i, -0.006]))


def image_msg(rgb: np.ndarray, ns: int, kind: str):
    if kind in ("png", "jpeg"):
        ok, buf = cv2.imencode(".png" if kind == "png" else ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        assert ok
        return T["sensor_msgs/msg/CompressedImage"](header=header(ns), format=kind, data=buf.reshape(-1))
    pixels = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)}[kind]
    h, w = pixels.shape[:2]
    ch = 1 if pixels.ndim == 2 else 3
    step = w * ch + 4  # padded rows, as some drivers send them
    data = np.zeros((h, step), np.uint8)
    data[:, : w * ch] = pixels.reshape(h, -1)
    return T["sensor_msgs/msg/Image"](header=header(ns), height=h, width=w, encoding=kind, is_bigendian=0,
                                      step=step, data=data.reshape(-1))  # fmt: skip


def camera_info(K: np.ndarray, w: int, h: int, model: str = "plumb_bob", d=(0.0, 0.0, 0.0, 0.0, 0.0)):
    P = np.zeros((3, 4))
    P[:, :3] = K
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(T0), height=h, width=w, distortion_model=model, d=np.asarray(d, np.float64),
        k=K.reshape(-1).astype(np.float64), r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip


def write_bag(
    path: Path,
    room: dict,
    storage: str = "sqlite3",
    image: str = "rgb8",
    pose: str = "tf",
    model: str = "plumb_bob",
    dist=(0.0, 0.0, 0.0, 0.0, 0.0),
    pose_shift_ns: int = 0,
    extra_images: int = 0,
    image_topic: str = IMAGE_TOPIC,
    p_matrix: np.ndarray | None = None,
) -> Path:
    """A bag with the room's images at 10 Hz, their camera info and poses (TF, PoseStamped or Odometry)."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    frames, poses, rgbs = room["frames"], room["poses"], room["rgb"]
    intr = frames[0].intrinsics
    with Writer(path, version=9, storage_plugin=plugin) as w:
        msgtype = "sensor_msgs/msg/CompressedImage" if image in ("png", "jpeg") else "sensor_msgs/msg/Image"
        topic = image_topic if msgtype.endswith("/Image") else image_topic + "/compressed"
        img_c = w.add_connection(topic, msgtype, typestore=TS)
        info_c = w.add_connection(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", typestore=TS)
        odo_c = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=TS)
        pose_c = w.add_connection("/camera_pose", "geometry_msgs/msg/PoseStamped", typestore=TS)
        tf_c = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=TS)
        static_c = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)

        def put(conn, ns, msg) -> None:
            w.write(conn, ns, TS.serialize_cdr(msg, conn.msgtype))

        tfm = T["tf2_msgs/msg/TFMessage"]
        static = [
            tf_stamped(T0, "map", "odom", STATIC_MAP_ODOM),
            tf_stamped(T0, "base_link", "camera_link", STATIC_BASE_CAM),
            tf_stamped(T0, "camera_link", "camera_optical_frame", BODY_TO_OPTICAL),
        ]
        put(static_c, T0 - DT, tfm(transforms=static))
        # odom -> base_link such that map -> camera_optical_frame is the room pose.
        to_base = invert_pose(STATIC_MAP_ODOM)
        from_base = STATIC_BASE_CAM @ BODY_TO_OPTICAL
        for i in range(len(frames) + extra_images):
            ns = T0 + i * DT
            if i < len(frames):
                info = camera_info(intr.K, intr.width, intr.height, model, dist)
                if p_matrix is not None:
                    info.p = p_matrix.reshape(-1)
                info.header = header(ns)
                put(info_c, ns, info)
            put(img_c, ns, image_msg(rgbs[i % len(frames)], ns, image))
            if i >= len(frames):
                continue
            for sign in (-1, 1):
                ps = ns + sign * HALF + pose_shift_ns
                cam = wiggle(poses[i], sign, i)
                if pose == "tf":
                    base = to_base @ cam @ invert_pose(from_base)
                    lidar = tf_stamped(ps, "base_link", "lidar", np.eye(4))
                    put(tf_c, ps, tfm(transforms=[lidar, tf_stamped(ps, "odom", "base_link", base)]))
                elif pose == "pose":
                    put(pose_c, ps, T["geometry_msgs/msg/PoseStamped"](header=header(ps, "map"), pose=ros_pose(cam)))
                else:
                    cov = T["geometry_msgs/msg/PoseWithCovariance"](pose=ros_pose(cam), covariance=np.zeros(36))
                    v = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
                    tw = T["geometry_msgs/msg/TwistWithCovariance"](
                        twist=T["geometry_msgs/msg/Twist"](linear=v, angular=v), covariance=np.zeros(36)
                    )
                    odo = T["nav_msgs/msg/Odometry"](
                        header=header(ps, "map"), child_frame_id="camera_optical_frame", pose=cov, twist=tw
                    )
                    put(odo_c, ps, odo)
    return path


def imported(scene: Path) -> list:
    frames = read_split(scene, "train").frames
    if (scene / "test").is_dir():
        frames += read_split(scene, "test").frames
    return sorted(frames, key=lambda f: f.name)


def assert_poses_match(frames: list, poses: np.ndarray) -> None:
    assert len(frames) == len(poses)
    for f, P in zip(frames, poses):
        t_err, r_err = pose_error(f.pose, P)
        assert t_err < 1e-3 and r_err < 0.01, (f.name, t_err, r_err)


def config(**kw) -> RosbagImportConfig:
    kw.setdefault("image_topic", IMAGE_TOPIC)
    if "pose_topic" not in kw:
        kw.setdefault("tf", "map:camera_optical_frame")
    return RosbagImportConfig(**kw)


@pytest.mark.parametrize(
    "storage, image, pose",
    [
        ("sqlite3", "rgb8", "tf"),
        ("mcap", "bgr8", "tf"),
        ("mcap", "rgb8", "pose"),
        ("sqlite3", "png", "odom"),
        ("sqlite3", "mono8", "pose"),
    ],
)
def test_bag_imports_to_the_original_scene(tmp_path: Path, room: dict, storage: str, image: str, pose: str) -> None:
    bag = write_bag(tmp_path / "bag", room, storage=storage, image=image, pose=pose)
    assert detect_format(bag) == "rosbag"
    topic = IMAGE_TOPIC + ("/compressed" if image == "png" else "")
    source = {"tf": {"tf": "map:camera_optical_frame"}, "pose": {"pose_topic": "/camera_pose", "optical": True},
              "odom": {"pose_topic": "/odom"}}[pose]  # fmt: skip
    cfg = RosbagImportConfig(image_topic=topic, camera_info_topic=INFO_TOPIC, **source)
    summary = import_rosbag(bag, tmp_path / "scene", cfg, test_every=0)
    assert (summary.train, summary.test, summary.skipped_no_pose, summary.images) == (12, 0, 0, 12)
    assert summary.optical and summary.undistorted == 0
    frames = imported(tmp_path / "scene")
    assert_poses_match(frames, room["poses"])
    for f, orig, rgb in zip(frames, room["frames"], room["rgb"]):
        np.testing.assert_allclose(f.intrinsics.K, orig.intrinsics.K, atol=1e-9)
        expected = np.repeat(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[..., None], 3, -1) if image == "mono8" else rgb
        np.testing.assert_array_equal(f.load_rgb(), expected)


def test_jpeg_and_camera_info_beside_the_image_topic(tmp_path: Path, room: dict) -> None:
    """CompressedImage jpeg decodes as OpenCV decodes it; a CameraInfo topic is looked for beside the image topic."""
    bag = write_bag(tmp_path / "bag", room, storage="mcap", image="jpeg", pose="pose")
    cfg = RosbagImportConfig(image_topic=IMAGE_TOPIC + "/compressed", pose_topic="/camera_pose", optical=True)
    # /camera/image_raw/compressed's namespace is /camera/image_raw: no camera_info there, the error says so.
    with pytest.raises(InputError, match="no CameraInfo topic '/camera/image_raw/camera_info'.*/camera/camera_info"):
        import_rosbag(bag, tmp_path / "scene", cfg)
    cfg.camera_info_topic = INFO_TOPIC
    import_rosbag(bag / "bag.mcap", tmp_path / "scene", cfg, test_every=0)  # the storage file alone works too
    frames = imported(tmp_path / "scene")
    assert_poses_match(frames, room["poses"])
    for f, rgb in zip(frames, room["rgb"]):
        jpeg = cv2.imdecode(image_msg(rgb, T0, "jpeg").data, cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(f.load_rgb(), cv2.cvtColor(jpeg, cv2.COLOR_BGR2RGB))


def test_tf_to_a_body_frame_turns_rep103_axes_to_optical(tmp_path: Path, room: dict) -> None:
    bag = write_bag(tmp_path / "bag", room)
    summary = import_rosbag(bag, tmp_path / "scene", config(tf="map:camera_link"), test_every=0)
    assert not summary.optical and "map -> odom -> base_link -> camera_link" in summary.pose_source
    assert_poses_match(imported(tmp_path / "scene"), room["poses"])
    # Declaring the body frame optical skips the turn: every pose is off by the fixed rotation.
    import_rosbag(bag, tmp_path / "wrong", config(tf="map:camera_link", optical=True), test_every=0)
    _, r_err = pose_error(imported(tmp_path / "wrong")[0].pose, room["poses"][0])
    assert r_err > 89


def test_tf_chain_between_two_leaves(tmp_path: Path, room: dict) -> None:
    """PARENT need not be an ancestor: lidar -> camera goes up to base_link and down again."""
    bag = write_bag(tmp_path / "bag", room)
    import_rosbag(bag, tmp_path / "scene", config(tf="lidar:camera_optical_frame"), test_every=0)
    expected = STATIC_BASE_CAM @ BODY_TO_OPTICAL  # lidar sits at base_link
    for f in imported(tmp_path / "scene"):
        np.testing.assert_allclose(f.pose, expected, atol=1e-9)


def test_every_min_baseline_and_time_block_split(tmp_path: Path, room: dict) -> None:
    bag = write_bag(tmp_path / "bag", room, extra_images=2)  # two images after the last pose: skipped
    summary = import_rosbag(bag, tmp_path / "s1", config(test_block=0.25), test_every=2)
    assert (summary.images, summary.skipped_no_pose) == (14, 2)
    assert any("skipped 2 of 14" in n for n in summary.notes)
    # Frame i is at 0.1 i s; blocks of 0.25 s: 0-2 | 3-4 | 5-7 | 8-9 | 10-11; blocks 1 and 3 to test.
    test_names = [f.name for f in read_split(tmp_path / "s1", "test").frames]
    assert [int(n.split("_")[0]) for n in test_names] == [3, 4, 8, 9]
    assert "by time" in summary.split_rule
    assert_poses_match(imported(tmp_path / "s1"), room["poses"])

    summary = import_rosbag(bag, tmp_path / "s2", config(every=3), test_every=0)
    assert (summary.train, summary.dropped_by_selection) == (4, 8)
    assert_poses_match(imported(tmp_path / "s2"), room["poses"][::3])

    steps = np.linalg.norm(np.diff(room["poses"][:, :3, 3], axis=0), axis=1)
    baseline = float(np.median(steps)) * 1.5
    summary = import_rosbag(bag, tmp_path / "s3", config(min_baseline=baseline), test_every=0)
    centres = np.stack([f.pose[:3, 3] for f in imported(tmp_path / "s3")])
    assert 1 < len(centres) < 12
    assert np.all(np.linalg.norm(np.diff(centres, axis=0), axis=1) >= baseline)


def test_plumb_bob_distortion_is_undone(tmp_path: Path, room: dict) -> None:
    dist = (-0.12, 0.03, 0.001, -0.002, 0.0)
    bag = write_bag(tmp_path / "bag", room, dist=dist)
    summary = import_rosbag(bag, tmp_path / "scene", config(), test_every=0)
    assert summary.undistorted == 12
    K = room["frames"][0].intrinsics.K
    expected, K_new = Undistorter()(room["rgb"][0], K, dist)
    frame = imported(tmp_path / "scene")[0]
    np.testing.assert_allclose(frame.intrinsics.K, K_new, atol=1e-9)
    np.testing.assert_array_equal(frame.load_rgb(), expected)
    assert not np.allclose(K_new, K)


def test_rectified_image_topic_takes_k_from_p(tmp_path: Path, room: dict) -> None:
    """image_rect is already undistorted: K comes from P and the distortion (of the raw image) is not applied."""
    K_rect = np.diag([1.1, 1.1, 1.0]) @ room["frames"][0].intrinsics.K  # differs from CameraInfo.k
    topic = "/camera/image_rect"
    bag = write_bag(tmp_path / "bag", room, dist=(-0.2, 0.0, 0.0, 0.0, 0.0), image_topic=topic,
                    p_matrix=np.hstack([K_rect, np.zeros((3, 1))]))  # fmt: skip
    summary = import_rosbag(bag, tmp_path / "scene", config(image_topic=topic), test_every=0)
    assert summary.undistorted == 0 and any("rectified" in n for n in summary.notes)
    frame = imported(tmp_path / "scene")[0]
    np.testing.assert_allclose(frame.intrinsics.K, K_rect, atol=1e-9)
    np.testing.assert_array_equal(frame.load_rgb(), room["rgb"][0])


def test_cli_imports_a_bag(tmp_path: Path, room: dict) -> None:
    bag = write_bag(tmp_path / "bag", room, storage="mcap")
    args = ["import", str(bag), "-o", str(tmp_path / "scene"), "--image-topic", IMAGE_TOPIC,
            "--tf", "map:camera_optical_frame", "--test-every", "0", "--every", "2",
            "--json", str(tmp_path / "r.json")]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert (report["format"], report["train"], report["dropped_by_selection"]) == ("rosbag", 6, 6)
    assert_poses_match(imported(tmp_path / "scene"), room["poses"][::2])


def cli_error(tmp_path: Path, args: list[str]) -> str:
    res = CliRunner().invoke(app, ["import", *args, "-o", str(tmp_path / "scene")])
    assert res.exit_code == 2, res.output
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.output
    assert not (tmp_path / "scene").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".scene")]  # no staging or temporary folder
    return res.stderr


def test_bad_bags_are_one_line_errors(tmp_path: Path, room: dict) -> None:
    bag = write_bag(tmp_path / "bag", room)
    tf = ["--tf", "map:camera_optical_frame"]
    err = cli_error(tmp_path, [str(bag), "--image-topic", "/nope", *tf])
    assert err.startswith(f"error: {bag}: no topic '/nope'") and IMAGE_TOPIC in err and "/tf_static" in err
    err = cli_error(tmp_path, [str(bag), *tf])
    assert "no image topic given" in err and IMAGE_TOPIC in err
    err = cli_error(tmp_path, [str(bag), "--image-topic", IMAGE_TOPIC, "--tf", "map:nowhere"])
    assert "no frame 'nowhere'" in err and "camera_link" in err
    err = cli_error(tmp_path, [str(bag), "--image-topic", IMAGE_TOPIC, "--pose-topic", "/camera_pose"])
    assert "--optical" in err and "--body" in err
    err = cli_error(tmp_path, [str(bag), "--image-topic", IMAGE_TOPIC, "--pose-topic", INFO_TOPIC, "--optical"])
    assert "not a pose topic" in err
    err = cli_error(tmp_path, [str(bag), "--image-topic", IMAGE_TOPIC])
    assert "exactly one pose source" in err

    late = write_bag(tmp_path / "late", room, pose="pose", pose_shift_ns=-60 * 10**9)  # poses a minute early
    err = cli_error(tmp_path, [str(late), "--image-topic", IMAGE_TOPIC, "--pose-topic", "/camera_pose", "--optical"])
    assert err.startswith(f"error: {late}: /camera_pose covers") and "images span" in err

    fisheye = write_bag(tmp_path / "fisheye", room, model="equidistant", dist=(0.1, 0.0, 0.0, 0.0))
    err = cli_error(tmp_path, [str(fisheye), "--image-topic", IMAGE_TOPIC, *tf])
    assert err.startswith(f"error: {fisheye}: {INFO_TOPIC}") and "'equidistant' is not supported" in err

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: [not, a, bag\n")
    err = cli_error(tmp_path, [str(broken), "--image-topic", IMAGE_TOPIC, *tf])
    assert err.startswith(f"error: {broken}: cannot read the bag")


def test_rosbag_options_refused_for_other_formats(tmp_path: Path) -> None:
    from tests.test_importers import make_transforms

    src = make_transforms(tmp_path / "t", n=2)
    with pytest.raises(InputError, match="do not apply"):
        import_scene(src, tmp_path / "scene", rosbag=RosbagImportConfig(image_topic="/x"))
