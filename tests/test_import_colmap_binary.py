"""COLMAP binary models written here in the documented format import exactly as the text model of the same cameras."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.apps.cli import app
from acesplat.core.errors import InputError
from acesplat.core.geometry import invert_pose, look_at, matrix_to_quat
from acesplat.core.scene import read_split
from acesplat.importers import detect_format, import_colmap_text, import_scene
from acesplat.importers.colmap_binary import import_colmap_binary
from tests.test_importers import write_image

W, H = 64, 48
# (camera_id, model name, model id, params): a distorted OPENCV camera and a PINHOLE one.
CAMERAS = [
    (3, "OPENCV", 4, (40.0, 41.0, 32.0, 24.0, -0.05, 0.01, 0.001, -0.002)),
    (7, "PINHOLE", 1, (50.0, 50.5, 31.0, 23.0)),
]


def images_table() -> list[tuple[int, np.ndarray, np.ndarray, int, str]]:
    """(image_id, qvec wxyz, tvec, camera_id, name) in COLMAP's world-to-camera convention, from known poses."""
    rows = []
    for i in range(5):
        c2w = look_at([0.3 * i, 1.0, 0.5 * np.sin(i)], [2.0, 0.2 * i, 0.0])
        w2c = invert_pose(c2w)
        rows.append((10 + i, matrix_to_quat(w2c[:3, :3]), w2c[:3, 3], CAMERAS[i % 2][0], f"sub dir/img {i}.png"))
    return rows


def write_text_model(model: Path) -> None:
    model.mkdir(parents=True, exist_ok=True)
    cams = "".join(f"{cid} {name} {W} {H} {' '.join(repr(p) for p in params)}\n" for cid, name, _, params in CAMERAS)
    (model / "cameras.txt").write_text("# cameras\n" + cams)
    lines = [
        f"{iid} {' '.join(repr(float(v)) for v in (*q, *t))} {cid} {name}\n1.5 2.5 -1 3.0 4.0 17\n"
        for iid, q, t, cid, name in images_table()
    ]
    (model / "images.txt").write_text("# images\n" + "".join(lines))


def cameras_bin() -> bytes:
    out = struct.pack("<Q", len(CAMERAS))
    for cid, _, model_id, params in CAMERAS:
        out += struct.pack("<iiQQ", cid, model_id, W, H) + struct.pack(f"<{len(params)}d", *params)
    return out


def images_bin() -> bytes:
    out = struct.pack("<Q", len(images_table()))
    for iid, q, t, cid, name in images_table():
        out += struct.pack("<i7di", iid, *q, *t, cid) + name.encode() + b"\0"
        points = [(1.5, 2.5, -1), (3.0, 4.0, 17)]
        out += struct.pack("<Q", len(points)) + b"".join(struct.pack("<ddq", *p) for p in points)
    return out


def make_project(root: Path, binary: bool = True, text: bool = False) -> Path:
    model = root / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    if binary:
        (model / "cameras.bin").write_bytes(cameras_bin())
        (model / "images.bin").write_bytes(images_bin())
        (model / "points3D.bin").write_bytes(struct.pack("<Q", 0))
    if text:
        write_text_model(model)
    for i, (*_, name) in enumerate(images_table()):
        write_image(root / "images" / name, seed=i)
    return model


def scene_records(scene: Path) -> list[tuple]:
    out = []
    for split in ("train", "test"):
        for f in read_split(scene, split).frames:
            out.append((split, f.name, f.pose, f.intrinsics, f.load_rgb()))
    return out


def test_binary_model_imports_like_the_text_model(tmp_path: Path) -> None:
    make_project(tmp_path / "bin")
    make_project(tmp_path / "txt", binary=False, text=True)
    assert detect_format(tmp_path / "bin") == "colmap"
    summary_bin = import_scene(tmp_path / "bin", tmp_path / "s_bin", test_every=2)
    summary_txt = import_colmap_text(tmp_path / "txt", None, tmp_path / "s_txt", test_every=2)
    assert (summary_bin.format, summary_bin.train, summary_bin.test) == ("colmap", 2, 3)
    assert (summary_bin.undistorted, summary_bin.train, summary_bin.test) == (
        summary_txt.undistorted, summary_txt.train, summary_txt.test
    )  # fmt: skip
    a, b = scene_records(tmp_path / "s_bin"), scene_records(tmp_path / "s_txt")
    assert len(a) == len(b) == 5
    for (sa, na, pa, ia, ra), (sb, nb, pb, ib, rb) in zip(a, b):
        assert (sa, na, ia) == (sb, nb, ib)
        np.testing.assert_array_equal(pa, pb)
        np.testing.assert_array_equal(ra, rb)
    # The poses are the known camera-to-world ones.
    poses = {
        f.name.split("_", 1)[1]: f.pose
        for split in ("train", "test")
        for f in read_split(tmp_path / "s_bin", split).frames
    }
    for i in range(5):
        c2w = look_at([0.3 * i, 1.0, 0.5 * np.sin(i)], [2.0, 0.2 * i, 0.0])
        np.testing.assert_allclose(poses[f"img_{i}"], c2w, atol=1e-9)


def test_binary_file_paths_and_cli(tmp_path: Path) -> None:
    model = make_project(tmp_path / "p")
    assert detect_format(model / "images.bin") == "colmap"
    res = CliRunner().invoke(app, ["import", str(model / "cameras.bin"), "-o", str(tmp_path / "scene")])
    assert res.exit_code == 0, res.output
    assert "binary model" in res.stdout


def test_text_model_wins_when_both_are_present(tmp_path: Path) -> None:
    model = make_project(tmp_path / "p", binary=True, text=True)
    (model / "images.bin").write_bytes(b"garbage")  # never read
    import_scene(tmp_path / "p", tmp_path / "scene", test_every=0)
    assert len(read_split(tmp_path / "scene").frames) == 5


def corrupt_cases() -> list:
    good_cams, good_imgs = cameras_bin(), images_bin()
    return [
        ("images.bin", good_imgs[:-5], ["truncated"]),
        ("images.bin", good_imgs[:30], ["truncated", "5 images cannot fit"]),
        ("images.bin", good_imgs + b"\x00" * 3, ["3 unexpected bytes"]),
        ("images.bin", struct.pack("<Q", 10**12) + good_imgs[8:], ["cannot fit"]),
        ("images.bin", good_imgs.replace(b"img 0.png\0", b"img 0.png#"), ["image 0", "control characters"]),
        ("images.bin", b"\x01\x00", ["truncated", "number of images"]),
        ("cameras.bin", good_cams[:-1], ["truncated", "camera 1"]),
        ("cameras.bin", good_cams[:12] + struct.pack("<i", 99) + good_cams[16:], ["unknown model id 99"]),
        ("cameras.bin", good_cams[:12] + struct.pack("<i", 5) + good_cams[16:], ["OPENCV_FISHEYE", "not supported"]),
    ]


@pytest.mark.parametrize("name, data, words", corrupt_cases())
def test_corrupt_binary_model_is_one_line_error(tmp_path: Path, name: str, data: bytes, words: list[str]) -> None:
    model = make_project(tmp_path / "p")
    (model / name).write_bytes(data)
    with pytest.raises(InputError) as info:
        import_colmap_binary(tmp_path / "p", None, tmp_path / "scene")
    assert str(info.value).startswith(str(model / name)), str(info.value)
    for word in words:
        assert word in str(info.value), str(info.value)
    res = CliRunner().invoke(app, ["import", str(tmp_path / "p"), "-o", str(tmp_path / "scene")])
    assert res.exit_code == 2
    assert res.stderr.count("\n") == 1 and res.stderr.startswith(f"error: {model / name}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p"]  # nothing half-written


def test_missing_image_and_undefined_camera(tmp_path: Path) -> None:
    model = make_project(tmp_path / "p")
    (tmp_path / "p" / "images" / "sub dir" / "img 3.png").unlink()
    with pytest.raises(InputError, match="img 3.png.*does not exist"):
        import_colmap_binary(tmp_path / "p", None, tmp_path / "scene")
    (model / "cameras.bin").write_bytes(struct.pack("<Q", 1) + cameras_bin()[8 : 8 + 24 + 8 * 8])
    with pytest.raises(InputError, match="CAMERA_ID 7 is not defined in cameras.bin"):
        import_colmap_binary(tmp_path / "p", None, tmp_path / "scene")


def test_undistortion_matches_opencv(tmp_path: Path) -> None:
    """The OPENCV camera's images are undistorted as the text importer does (same K_new)."""
    make_project(tmp_path / "p")
    import_colmap_binary(tmp_path / "p", None, tmp_path / "scene", test_every=0)
    frame = read_split(tmp_path / "scene").frames[0]  # image 10, camera 3 (OPENCV)
    fx, fy, cx, cy, *dist = CAMERAS[0][3]
    K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])
    K_new, _ = cv2.getOptimalNewCameraMatrix(K, np.array(dist), (W, H), 0.0, (W, H))
    np.testing.assert_allclose(frame.intrinsics.K, K_new, atol=1e-9)
