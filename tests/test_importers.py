"""Importers on small hand-written transforms.json and COLMAP text files with hand-computed expected poses."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.apps.cli import app
from acesplat.core.errors import InputError
from acesplat.core.geometry import look_at
from acesplat.core.scene import read_rgb, read_split
from acesplat.importers import detect_format, import_colmap_text, import_scene, import_transforms_json

W, H = 64, 48

# A camera at C = (1, 2, 3) looking along world +x with world +z up, worked out by hand.
# OpenCV axes in world coordinates: x (right) = -y_w, y (down) = -z_w, z (forward) = +x_w.
C2W_CV = np.array([[0, 0, 1, 1], [-1, 0, 0, 2], [0, -1, 0, 3], [0, 0, 0, 1]], dtype=float)
# The same camera with OpenGL axes: x right = -y_w, y up = +z_w, z back = -x_w.
C2W_GL = np.array([[0, 0, -1, 1], [-1, 0, 0, 2], [0, 1, 0, 3], [0, 0, 0, 1]], dtype=float)
# COLMAP's world-to-camera for it: R = R_c2w^T = [[0,-1,0],[0,0,-1],[1,0,0]], t = -R C = (2, 3, -1);
# trace 0 -> w = 1/2, x = (R21 - R12)/4w = 1/2, y = (R02 - R20)/4w = -1/2, z = (R10 - R01)/4w = 1/2.
COLMAP_LINE = "0.5 0.5 -0.5 0.5 2 3 -1"


def write_image(path: Path, seed: int = 0, w: int = W, h: int = H) -> np.ndarray:
    """A random RGB image written to ``path`` (format from its suffix); returns the RGB array."""
    rgb = np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return rgb


def gl_pose(i: int) -> list:
    """OpenGL camera-to-world of frame i: the hand-made camera moved along +y by i."""
    T = C2W_GL.copy()
    T[1, 3] += i
    return T.tolist()


def make_transforms(root: Path, n: int = 3, extra: dict | None = None, frame_extra: dict | None = None) -> Path:
    frames = []
    for i in range(n):
        write_image(root / "images" / f"img{i}.png", seed=i)
        frames.append({"file_path": f"images/img{i}.png", "transform_matrix": gl_pose(i), **(frame_extra or {})})
    data = {"fl_x": 40.0, "fl_y": 41.0, "cx": 32.0, "cy": 24.0, "w": W, "h": H, "frames": frames, **(extra or {})}
    path = root / "transforms.json"
    path.write_text(json.dumps(data))
    return path


def rewrite(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def expect_input_error(fn, *words: str) -> InputError:
    with pytest.raises(InputError) as info:
        fn()
    for word in words:
        assert word in str(info.value), str(info.value)
    return info.value


# ============================================================ transforms.json


def test_transforms_pose_flip_and_intrinsics(tmp_path: Path) -> None:
    src = make_transforms(tmp_path / "src", n=1)
    summary = import_transforms_json(src, tmp_path / "scene", test_every=0)
    assert (summary.train, summary.test) == (1, 0)
    frame = read_split(tmp_path / "scene", "train").frames[0]
    np.testing.assert_allclose(frame.pose, C2W_CV, atol=1e-12)
    np.testing.assert_allclose(frame.pose, look_at([1, 2, 3], [2, 2, 3]), atol=1e-12)  # same camera, from core
    # Principal point moves from the pixel-corner convention (32, 24) to OpenCV's (31.5, 23.5).
    np.testing.assert_allclose(frame.intrinsics.K, [[40, 0, 31.5], [0, 41, 23.5], [0, 0, 1]])
    np.testing.assert_array_equal(frame.load_rgb(), read_rgb(tmp_path / "src" / "images" / "img0.png"))


def test_transforms_point_in_front_of_camera_projects_in_front(tmp_path: Path) -> None:
    """A world point ahead of the camera and above its axis: z > 0 and above the principal point (v < cy)."""
    src = make_transforms(tmp_path / "src", n=1)
    import_transforms_json(src, tmp_path / "scene", test_every=0)
    frame = read_split(tmp_path / "scene").frames[0]
    X_world = np.array([4.0, 2.0, 3.5])  # 3 m ahead (+x), 0.5 m up (+z)
    R, t = frame.pose[:3, :3], frame.pose[:3, 3]
    X_cam = R.T @ (X_world - t)
    np.testing.assert_allclose(X_cam, [0.0, -0.5, 3.0], atol=1e-12)
    assert frame.intrinsics.project(X_cam[None])[0, 1] < frame.intrinsics.cy


def test_transforms_camera_angle_and_extensionless_paths(tmp_path: Path) -> None:
    """Blender style: only camera_angle_x, file_path without extension, image size from the file."""
    root = tmp_path / "src"
    write_image(root / "train" / "r_0.png")
    data = {"camera_angle_x": math.pi / 2, "frames": [{"file_path": "./train/r_0", "transform_matrix": gl_pose(0)}]}
    (root / "transforms.json").write_text(json.dumps(data))
    import_transforms_json(root, tmp_path / "scene", test_every=0)  # the folder works as well as the file
    intr = read_split(tmp_path / "scene").frames[0].intrinsics
    # fx = (w / 2) / tan(fov / 2) = 32 / tan(45 deg) = 32; fy = fx; principal point at the centre (w - 1) / 2.
    np.testing.assert_allclose([intr.fx, intr.fy, intr.cx, intr.cy], [32.0, 32.0, 31.5, 23.5], atol=1e-12)


def test_transforms_camera_angle_y_and_per_frame_override(tmp_path: Path) -> None:
    src = make_transforms(
        tmp_path / "src", n=2, extra={"fl_x": None, "fl_y": None, "camera_angle_x": 1.0, "camera_angle_y": 0.8}
    )
    rewrite(src, lambda d: d["frames"][1].update({"fl_x": 70.0, "fl_y": 71.0, "cx": 30.0}))
    import_transforms_json(src, tmp_path / "scene", test_every=0)
    f0, f1 = read_split(tmp_path / "scene").frames
    np.testing.assert_allclose([f0.intrinsics.fx, f0.intrinsics.fy], [32 / math.tan(0.5), 24 / math.tan(0.4)])
    np.testing.assert_allclose(
        [f1.intrinsics.fx, f1.intrinsics.fy, f1.intrinsics.cx, f1.intrinsics.cy], [70, 71, 29.5, 23.5]
    )


def test_transforms_split_every_nth_in_natural_order(tmp_path: Path) -> None:
    root = tmp_path / "src"
    frames = []
    for i in range(11):  # written in scrambled order; img2 must sort before img10
        j = (i * 7) % 11
        write_image(root / f"img{j}.png", seed=j)
        frames.append({"file_path": f"img{j}.png", "transform_matrix": gl_pose(j)})
    (root / "transforms.json").write_text(json.dumps({"fl_x": 40.0, "frames": frames}))
    summary = import_transforms_json(root / "transforms.json", tmp_path / "scene", test_every=4)
    assert (summary.train, summary.test) == (8, 3)
    test = read_split(tmp_path / "scene", "test")
    train = read_split(tmp_path / "scene", "train")
    assert [f.name for f in test.frames] == ["00000_img0", "00004_img4", "00008_img8"]
    assert [f.name for f in train.frames][:3] == ["00001_img1", "00002_img2", "00003_img3"]
    np.testing.assert_allclose(test.frames[1].pose[1, 3], 2.0 + 4)  # img4's pose travelled with it


def test_transforms_default_split_is_every_8th(tmp_path: Path) -> None:
    src = make_transforms(tmp_path / "src", n=9)
    summary = import_transforms_json(src, tmp_path / "scene")
    assert (summary.train, summary.test) == (7, 2)
    assert "every 8-th" in summary.split_rule


def test_transforms_blender_split_files(tmp_path: Path) -> None:
    root = tmp_path / "src"
    for split, n in (("train", 3), ("test", 2), ("val", 1)):
        frames = []
        for i in range(n):
            write_image(root / split / f"r_{i}.png", seed=i)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": gl_pose(i)})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.9, "frames": frames}))
    assert detect_format(root) == "transforms"
    summary = import_transforms_json(root, tmp_path / "scene", test_every=2)
    assert (summary.train, summary.test) == (3, 2)
    assert summary.split_rule == "split given by the source files"
    assert any("transforms_val.json" in n for n in summary.notes)
    assert len(read_split(tmp_path / "scene", "test")) == 2


def test_transforms_applied_transform_is_noted_not_applied(tmp_path: Path) -> None:
    applied = [[0, 1, 0, 5], [1, 0, 0, 6], [0, 0, -1, 7]]
    src = make_transforms(tmp_path / "src", n=1, extra={"applied_transform": applied})
    summary = import_transforms_json(src, tmp_path / "scene", test_every=0)
    assert any("applied_transform" in n and "not applied" in n for n in summary.notes)
    np.testing.assert_allclose(read_split(tmp_path / "scene").frames[0].pose, C2W_CV, atol=1e-12)


def test_transforms_3x4_matrix_accepted(tmp_path: Path) -> None:
    src = make_transforms(tmp_path / "src", n=1)
    rewrite(src, lambda d: d["frames"][0].update({"transform_matrix": gl_pose(0)[:3]}))
    import_transforms_json(src, tmp_path / "scene", test_every=0)
    np.testing.assert_allclose(read_split(tmp_path / "scene").frames[0].pose, C2W_CV, atol=1e-12)


def test_transforms_downscaled_images_rescale_intrinsics(tmp_path: Path) -> None:
    """Images at half the stated w x h (nerfstudio images_2) keep the camera geometry: K is rescaled."""
    src = make_transforms(tmp_path / "src", n=1)
    write_image(tmp_path / "half" / "img0.png", w=W // 2, h=H // 2)
    summary = import_transforms_json(src, tmp_path / "scene", test_every=0, images_dir=tmp_path / "half")
    assert summary.rescaled == 1
    intr = read_split(tmp_path / "scene").frames[0].intrinsics
    # fx: 40 * 0.5; cx: OpenCV 31.5 -> (31.5 + 0.5) * 0.5 - 0.5 = 15.5 (= corner-convention 32 * 0.5, minus 0.5).
    np.testing.assert_allclose([intr.fx, intr.fy, intr.cx, intr.cy], [20.0, 20.5, 15.5, 11.5])
    assert (intr.width, intr.height) == (W // 2, H // 2)


def test_transforms_non_uniform_size_mismatch_refused(tmp_path: Path) -> None:
    src = make_transforms(tmp_path / "src", n=1)
    img = tmp_path / "src" / "images" / "img0.png"
    write_image(img, w=W, h=H // 2)
    expect_input_error(
        lambda: import_transforms_json(src, tmp_path / "scene", test_every=0), str(img), "64x24", "64x48"
    )
    assert not (tmp_path / "scene").exists()


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda d: d.pop("frames"), ["'frames'"]),
        (lambda d: d.update(frames=[]), ["'frames'"]),
        (lambda d: d["frames"][1].pop("transform_matrix"), ["frames[1]", "missing 'transform_matrix'"]),
        (lambda d: d["frames"][1].pop("file_path"), ["frames[1]", "missing 'file_path'"]),
        (lambda d: d["frames"][2].update(file_path="images/gone.png"), ["frames[2]", "gone.png", "not found"]),
        (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(3, float("nan")), ["frames[0]", "non-finite"]),
        (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(0, 2.0), ["frames[0]", "orthonormal"]),
        (lambda d: d["frames"][0]["transform_matrix"][1].pop(), ["frames[0]", "4x4 list of numbers"]),
        (lambda d: d["frames"][0].update(transform_matrix=[[1, 2], [3]]), ["frames[0]", "4x4"]),
        (lambda d: [d.pop(k) for k in ("fl_x", "fl_y")], ["frames[0]", "no focal length"]),
        (lambda d: d.update(fl_x=-40.0), ["'fl_x' must be positive"]),
        (lambda d: d.update(fl_x="40"), ["'fl_x' must be a number"]),
        (lambda d: d.update(cx=float("inf")), ["'cx' is not finite"]),
        (lambda d: d.pop("h"), ["'w' and 'h'"]),
        (lambda d: d.update(w=63.5), ["whole number"]),
        (lambda d: d.update(camera_model="OPENCV_FISHEYE"), ["OPENCV_FISHEYE", "not supported"]),
        (lambda d: d.update(camera_model="EQUIRECTANGULAR"), ["EQUIRECTANGULAR", "not supported"]),
        (lambda d: d.update(k4=0.1), ["'k4'", "fisheye"]),
        (lambda d: d.update(camera_angle_x=4.0, fl_x=None), ["camera_angle_x"]),
    ],
)
def test_transforms_bad_input_names_file(tmp_path: Path, edit, words: list[str]) -> None:
    src = make_transforms(tmp_path / "src", n=3)
    rewrite(src, edit)
    err = expect_input_error(lambda: import_transforms_json(src, tmp_path / "scene"), str(src), *words)
    assert str(err).startswith(str(src))
    assert not (tmp_path / "scene").exists()


def test_transforms_invalid_json_reports_line(tmp_path: Path) -> None:
    src = tmp_path / "transforms.json"
    src.write_text('{\n  "fl_x": 40,\n  "frames": [\n    {"file_path": "a.png",,}\n  ]\n}\n')
    expect_input_error(lambda: import_transforms_json(src, tmp_path / "scene"), str(src), "not valid JSON", "line 4")


def test_transforms_corrupt_image_leaves_no_scene(tmp_path: Path) -> None:
    src = make_transforms(tmp_path / "src", n=3)
    bad = tmp_path / "src" / "images" / "img2.png"
    bad.write_bytes(b"\x89PNG not really")
    expect_input_error(lambda: import_transforms_json(src, tmp_path / "scene"), str(bad), "cannot decode")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no scene, no temporary folder left


def test_output_must_be_new_or_empty(tmp_path: Path) -> None:
    src = make_transforms(tmp_path / "src", n=2)
    (tmp_path / "scene").mkdir()
    import_transforms_json(src, tmp_path / "scene", test_every=0)  # an empty folder is fine
    expect_input_error(
        lambda: import_transforms_json(src, tmp_path / "scene"), str(tmp_path / "scene"), "not an empty folder"
    )


def test_bad_test_every(tmp_path: Path) -> None:
    src = make_transforms(tmp_path / "src", n=2)
    expect_input_error(lambda: import_transforms_json(src, tmp_path / "s", test_every=-1), "test_every")
    expect_input_error(lambda: import_transforms_json(src, tmp_path / "s", test_every=1), "no training frame")


# ============================================================ COLMAP text


def write_colmap(
    root: Path,
    cameras: str = "1 PINHOLE 64 48 40 41 32 24\n",
    images: str | None = None,
    names: tuple[str, ...] = ("a.png",),
) -> Path:
    model = root / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    (model / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + cameras
    )
    if images is None:
        images = "".join(f"{i + 1} {COLMAP_LINE} 1 {n}\n\n" for i, n in enumerate(names))
    (model / "images.txt").write_text("# Image list with two lines of data per image:\n" + images)
    for i, n in enumerate(names):
        write_image(root / "images" / n, seed=i)
    return model


def test_colmap_quaternion_inversion_hand_case(tmp_path: Path) -> None:
    write_colmap(tmp_path / "proj")
    summary = import_colmap_text(tmp_path / "proj", None, tmp_path / "scene", test_every=0)  # finds sparse/0, images/
    assert summary.format == "colmap" and summary.train == 1
    frame = read_split(tmp_path / "scene").frames[0]
    np.testing.assert_allclose(frame.pose, C2W_CV, atol=1e-12)
    np.testing.assert_allclose(frame.intrinsics.K, [[40, 0, 31.5], [0, 41, 23.5], [0, 0, 1]])


def test_colmap_rotation_about_z_with_translation(tmp_path: Path) -> None:
    # w2c: R = +90 deg about z, t = (1, 0, 0). c2w: R^T = [[0,1,0],[-1,0,0],[0,0,1]], C = -R^T t = (0, 1, 0).
    s = math.sqrt(0.5)
    write_colmap(tmp_path / "proj", images=f"7 {s} 0 0 {s} 1 0 0 1 a.png\n\n")
    import_colmap_text(
        tmp_path / "proj" / "sparse" / "0", tmp_path / "proj" / "images", tmp_path / "scene", test_every=0
    )
    expected = np.array([[0, 1, 0, 0], [-1, 0, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(read_split(tmp_path / "scene").frames[0].pose, expected, atol=1e-12)


def test_colmap_points_lines_names_and_split(tmp_path: Path) -> None:
    """Empty and non-empty 2D-points lines, a name with a space, a subfolder, no final newline."""
    names = ("frame 1.png", "sub/frame2.png", "frame10.png", "frame3.jpg")
    lines = [
        f"1 {COLMAP_LINE} 1 {names[0]}", "10.5 20.25 -1 30 40 7",
        f"2 {COLMAP_LINE} 1 {names[1]}", "",
        f"3 {COLMAP_LINE} 1 {names[2]}", "1 2 3",
        f"4 {COLMAP_LINE} 1 {names[3]}",
    ]  # fmt: skip
    write_colmap(tmp_path / "proj", images="\n".join(lines), names=names)
    summary = import_colmap_text(tmp_path / "proj", None, tmp_path / "scene", test_every=2)
    assert (summary.train, summary.test) == (2, 2)
    # natural order: "frame3" < "frame10" (numbers compare as numbers) < "frame 1" < "sub/frame2"; test = 0 and 2
    assert [f.name for f in read_split(tmp_path / "scene", "test").frames] == ["00000_frame3", "00002_frame_1"]
    assert [f.name for f in read_split(tmp_path / "scene", "train").frames] == ["00001_frame10", "00003_frame2"]


def test_colmap_simple_pinhole(tmp_path: Path) -> None:
    write_colmap(tmp_path / "proj", cameras="3 SIMPLE_PINHOLE 64 48 50 30 20\n", images=f"1 {COLMAP_LINE} 3 a.png\n\n")
    import_colmap_text(tmp_path / "proj", None, tmp_path / "scene", test_every=0)
    np.testing.assert_allclose(
        read_split(tmp_path / "scene").frames[0].intrinsics.K, [[50, 0, 29.5], [0, 50, 19.5], [0, 0, 1]]
    )


def blob_at(points: np.ndarray, w: int = 96, h: int = 72, sigma: float = 1.6) -> np.ndarray:
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    img = np.zeros((h, w), np.float64)
    for pu, pv in points:
        img += np.exp(-((u - pu) ** 2 + (v - pv) ** 2) / (2 * sigma**2))
    return np.clip(img * 255, 0, 255).astype(np.uint8)


def local_centroid(img: np.ndarray, near: np.ndarray, r: int = 5) -> np.ndarray:
    u0, v0 = int(round(near[0])), int(round(near[1]))
    patch = img[v0 - r : v0 + r + 1, u0 - r : u0 + r + 1].astype(np.float64)
    dv, du = np.mgrid[-r : r + 1, -r : r + 1]
    return np.array([u0 + (du * patch).sum() / patch.sum(), v0 + (dv * patch).sum() / patch.sum()])


@pytest.mark.parametrize(
    "model, params, dist",
    [
        ("SIMPLE_RADIAL", "60 {cx} {cy} -0.25", [-0.25, 0, 0, 0]),
        ("RADIAL", "60 {cx} {cy} -0.2 0.05", [-0.2, 0.05, 0, 0]),
        ("OPENCV", "60 62 {cx} {cy} -0.2 0.04 0.003 -0.002", [-0.2, 0.04, 0.003, -0.002]),
        (
            "FULL_OPENCV",
            "60 62 {cx} {cy} -0.2 0.04 0.003 -0.002 0.01 0.02 0.0 0.01",
            [-0.2, 0.04, 0.003, -0.002, 0.01, 0.02, 0.0, 0.01],
        ),
    ],
)
def test_colmap_undistortion_puts_points_where_new_K_projects_them(
    tmp_path: Path, model: str, params: str, dist: list
) -> None:
    """Brute force: blobs drawn at OpenCV-distorted projections land at the imported K's pinhole projections."""
    w, h = 96, 72
    cx_cv, cy_cv = 47.0, 36.5
    p = [float(v) for v in params.format(cx=cx_cv + 0.5, cy=cy_cv + 0.5).split()]  # COLMAP's +0.5 principal point
    fx, fy = (p[0], p[0]) if model.startswith(("SIMPLE", "RADIAL")) else (p[0], p[1])
    K_cv = np.array([[fx, 0, cx_cv], [0, fy, cy_cv], [0, 0, 1]])
    X = np.array([[-0.45, -0.3, 1.0], [0.42, -0.28, 1.0], [-0.4, 0.3, 1.0], [0.44, 0.32, 1.0], [0.05, 0.02, 1.0]])
    distorted, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K_cv, np.array(dist))
    root = tmp_path / "proj"
    write_colmap(
        root,
        cameras=f"1 {model} {w} {h} {params.format(cx=cx_cv + 0.5, cy=cy_cv + 0.5)}\n",
        images="1 1 0 0 0 0 0 0 1 a.png\n\n",
    )
    cv2.imwrite(str(root / "images" / "a.png"), blob_at(distorted[:, 0], w, h))
    summary = import_colmap_text(root, None, tmp_path / "scene", test_every=0)
    assert summary.undistorted == 1
    frame = read_split(tmp_path / "scene").frames[0]
    np.testing.assert_allclose(frame.pose, np.eye(4), atol=1e-12)
    img = frame.load_rgb()[..., 0]
    expected = frame.intrinsics.project(X)
    for uv_exp in expected:
        np.testing.assert_allclose(local_centroid(img, uv_exp), uv_exp, atol=0.15)
    # Meaningful: without undistortion the corner blobs would sit pixels away from the pinhole projection.
    assert np.abs(expected - distorted[:, 0]).max() > 1.0


@pytest.mark.parametrize(
    "cameras, images, words",
    [
        ("1 KANNALA 64 48 1 2 3 4\n", None, ["cameras.txt", "line 3", "unknown camera model 'KANNALA'"]),
        (
            "1 OPENCV_FISHEYE 64 48 40 40 32 24 0 0 0 0\n",
            None,
            ["cameras.txt", "line 3", "OPENCV_FISHEYE", "image_undistorter"],
        ),
        ("1 PINHOLE 64 48 40 41 32\n", None, ["cameras.txt", "line 3", "needs 4 parameters"]),
        ("1 PINHOLE 64 48 40 nan 32 24\n", None, ["cameras.txt", "line 3", "non-finite"]),
        ("1 PINHOLE 64 48 40 4l 32 24\n", None, ["cameras.txt", "line 3", "must be numbers"]),
        ("1 SIMPLE_PINHOLE 64 48 -5 32 24\n", None, ["cameras.txt", "line 3", "focal length must be positive"]),
        ("1 PINHOLE 0 48 40 41 32 24\n", None, ["cameras.txt", "line 3", "size must be positive"]),
        ("x PINHOLE 64 48 40 41 32 24\n", None, ["cameras.txt", "line 3", "CAMERA_ID"]),
        (
            "1 PINHOLE 64 48 40 41 32 24\n1 PINHOLE 64 48 40 41 32 24\n",
            None,
            ["cameras.txt", "line 4", "defined twice"],
        ),
        ("# nothing\n", None, ["cameras.txt", "no cameras"]),
        (None, f"1 {COLMAP_LINE} 2 a.png\n\n", ["images.txt", "line 2", "CAMERA_ID 2 is not defined"]),
        (None, "1 0.5 0.5 -0.5 0.5 2 3 1\n\n", ["images.txt", "line 2", "expected IMAGE_ID"]),
        (None, "1 0.5 0.5 -0.5 0.5 2 3 inf 1 a.png\n\n", ["images.txt", "line 2", "non-finite"]),
        (None, "1 0.5 0.5 -0.5 zero 2 3 1 1 a.png\n\n", ["images.txt", "line 2", "must be numbers"]),
        (None, "1 0 0 0 0 2 3 1 1 a.png\n\n", ["images.txt", "line 2", "quaternion is zero"]),
        (None, f"1 {COLMAP_LINE} 1 a.png\n2 {COLMAP_LINE} 1 a.png\n", ["images.txt", "line 3", "2D points line"]),
        (None, f"1 {COLMAP_LINE} 1 a.png\n\n2 {COLMAP_LINE} 1 a.png\n\n", ["listed twice"]),
        (None, "# none\n", ["images.txt", "no images"]),
    ],
)
def test_colmap_bad_model_names_file_and_line(tmp_path: Path, cameras, images, words: list[str]) -> None:
    kwargs = {}
    if cameras is not None:
        kwargs["cameras"] = cameras
    if images is not None:
        kwargs["images"] = images
    write_colmap(tmp_path / "proj", **kwargs)
    expect_input_error(lambda: import_colmap_text(tmp_path / "proj", None, tmp_path / "scene"), *words)
    assert not (tmp_path / "scene").exists()


def test_colmap_missing_image_names_image_and_line(tmp_path: Path) -> None:
    model = write_colmap(tmp_path / "proj", names=("a.png", "b.png"))
    (tmp_path / "proj" / "images" / "b.png").unlink()
    err = expect_input_error(
        lambda: import_colmap_text(tmp_path / "proj", None, tmp_path / "scene"),
        str(tmp_path / "proj" / "images" / "b.png"), str(model / "images.txt"), "line 4", "does not exist",
    )  # fmt: skip
    assert str(err).startswith(str(tmp_path / "proj" / "images" / "b.png"))


def test_colmap_image_size_differs_from_camera(tmp_path: Path) -> None:
    write_colmap(tmp_path / "proj")
    write_image(tmp_path / "proj" / "images" / "a.png", w=32, h=24)  # half size: rescaled
    summary = import_colmap_text(tmp_path / "proj", None, tmp_path / "scene", test_every=0)
    assert summary.rescaled == 1
    intr = read_split(tmp_path / "scene").frames[0].intrinsics
    np.testing.assert_allclose([intr.fx, intr.fy, intr.cx, intr.cy], [20.0, 20.5, 15.5, 11.5])
    write_image(tmp_path / "proj" / "images" / "a.png", w=40, h=24)  # not a uniform rescale: refused
    expect_input_error(
        lambda: import_colmap_text(tmp_path / "proj", None, tmp_path / "scene2", test_every=0), "a.png", "40x24"
    )


def test_colmap_model_discovery_errors(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    expect_input_error(lambda: import_colmap_text(tmp_path / "empty", None, tmp_path / "s"), "no COLMAP text model")
    (tmp_path / "bin" / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "bin" / "sparse" / "0" / "cameras.bin").write_bytes(b"\x01\x00")
    expect_input_error(
        lambda: import_colmap_text(tmp_path / "bin", None, tmp_path / "s"), "binary COLMAP model", "model_converter"
    )
    model = write_colmap(tmp_path / "noimg")
    for f in (tmp_path / "noimg" / "images").iterdir():
        f.unlink()
    (tmp_path / "noimg" / "images").rmdir()
    expect_input_error(lambda: import_colmap_text(model, None, tmp_path / "s"), str(model), "no images/ folder")
    expect_input_error(
        lambda: import_colmap_text(model, tmp_path / "nowhere", tmp_path / "s"), "nowhere", "does not exist"
    )


# ============================================================ dispatch and CLI


def test_detect_format(tmp_path: Path) -> None:
    src = make_transforms(tmp_path / "t", n=1)
    write_colmap(tmp_path / "c")
    assert detect_format(src) == "transforms" and detect_format(src.parent) == "transforms"
    assert (
        detect_format(tmp_path / "c") == "colmap"
        and detect_format(tmp_path / "c" / "sparse" / "0" / "images.txt") == "colmap"
    )
    expect_input_error(lambda: detect_format(tmp_path / "missing"), "does not exist")
    (tmp_path / "x.txt").write_text("hi")
    expect_input_error(lambda: detect_format(tmp_path / "x.txt"), "not a transforms")
    summary = import_scene(
        tmp_path / "c" / "sparse" / "0" / "images.txt",
        tmp_path / "scene",
        images_dir=tmp_path / "c" / "images",
        test_every=0,
    )
    assert summary.format == "colmap"


def test_cli_import_transforms_and_colmap(tmp_path: Path) -> None:
    runner = CliRunner()
    make_transforms(tmp_path / "t", n=4)
    res = runner.invoke(
        app,
        [
            "import",
            str(tmp_path / "t"),
            "-o",
            str(tmp_path / "s1"),
            "--test-every",
            "2",
            "--json",
            str(tmp_path / "r.json"),
        ],
    )
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert (report["format"], report["train"], report["test"]) == ("transforms", 2, 2)
    assert len(read_split(tmp_path / "s1", "test")) == 2
    write_colmap(tmp_path / "c", names=("a.png", "b.png"))
    res = runner.invoke(
        app,
        [
            "import",
            str(tmp_path / "c"),
            "-o",
            str(tmp_path / "s2"),
            "--format",
            "colmap",
            "--images",
            str(tmp_path / "c" / "images"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert "train 1, test 1" in res.stdout


def test_cli_bad_input_is_one_line_exit_2(tmp_path: Path) -> None:
    model = write_colmap(tmp_path / "c", cameras="1 FOV 64 48 40 40 32 24 0.1\n")
    res = CliRunner().invoke(app, ["import", str(tmp_path / "c"), "-o", str(tmp_path / "s")])
    assert res.exit_code == 2
    assert res.stderr.count("\n") == 1 and res.stderr.startswith(f"error: {model / 'cameras.txt'}: line 3")
    assert "Traceback" not in res.output
    res = CliRunner().invoke(app, ["import", str(tmp_path / "c"), "-o", str(tmp_path / "s"), "--format", "transforms"])
    assert res.exit_code == 2 and "transforms.json" in res.stderr


def test_importers_do_not_import_torch() -> None:
    code = "import sys, acesplat.importers, acesplat.apps.import_cmd; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
