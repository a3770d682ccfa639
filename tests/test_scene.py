"""The ACE scene layout reader against hand-made folders: every bad input names the offending file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from acesplat.core.errors import InputError
from acesplat.core.geometry import RIGID_TOL, make_pose, quat_to_matrix
from acesplat.core.scene import read_depth, read_rgb, read_split, write_frame

W, H = 40, 30


def pose_text(T: np.ndarray) -> str:
    return "\n".join(" ".join(repr(float(v)) for v in row) for row in T) + "\n"


def make_split(scene: Path, split: str = "train", n: int = 3, calib: str = "50\n", ext: str = ".png") -> Path:
    """A valid hand-made split: n random images, poses, single-focal calibrations."""
    base = scene / split
    for sub in ("rgb", "poses", "calibration"):
        (base / sub).mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(len(split))
    for i in range(n):
        img = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        assert cv2.imwrite(str(base / "rgb" / f"frame{i:03d}{ext}"), img)
        T = make_pose(quat_to_matrix(rng.normal(size=4)), rng.normal(size=3))
        (base / "poses" / f"frame{i:03d}.txt").write_text(pose_text(T))
        (base / "calibration" / f"frame{i:03d}.txt").write_text(calib)
    return base


def expect_error(scene: Path, path: Path, *words: str, split: str = "train") -> InputError:
    with pytest.raises(InputError) as info:
        read_split(scene, split)
    msg = str(info.value)
    assert msg.startswith(str(path)), msg  # the one-line report names the offending file first
    for word in words:
        assert word in msg, msg
    return info.value


# ---------------------------------------------------------------- good input


def test_reads_valid_split(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=3)
    (base / "poses" / ".DS_Store").write_text("junk")  # hidden files are not frames
    (base / "rgb" / "notes.txt").write_text("not an image")  # nor are non-image files in rgb/
    split = read_split(tmp_path, "train")
    assert len(split) == 3 and [f.name for f in split.frames] == ["frame000", "frame001", "frame002"]
    assert split.poses.shape == (3, 4, 4)
    assert split.frames[0].load_rgb().shape == (H, W, 3)


def test_single_focal_puts_principal_point_at_image_centre(tmp_path: Path) -> None:
    make_split(tmp_path, n=1, calib="525.5\n")
    intr = read_split(tmp_path).frames[0].intrinsics
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) == (525.5, 525.5, W / 2, H / 2, W, H)


def test_full_K_calibration(tmp_path: Path) -> None:
    make_split(tmp_path, n=1, calib="60 0 19.5\n0 61 14.25\n0 0 1\n")
    intr = read_split(tmp_path).frames[0].intrinsics
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (60.0, 61.0, 19.5, 14.25)


def test_pose_just_within_tolerance_is_accepted(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=1)
    T = np.eye(4)
    T[0, 0] = 1 + 0.49 * RIGID_TOL  # |R^T R - I| = 0.98e-4, det - 1 = 0.49e-4
    (base / "poses" / "frame000.txt").write_text(pose_text(T))
    np.testing.assert_array_equal(read_split(tmp_path).frames[0].pose, T)


def test_write_frame_read_split_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    written = []
    for i in range(3):
        rgb = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        T = make_pose(quat_to_matrix(rng.normal(size=4)), rng.normal(size=3) * 10)
        K = np.array([[45.0 + i, 0, 19.3], [0, 46.0, 14.9], [0, 0, 1]])
        write_frame(tmp_path / "test", f"f{i}", rgb, T, K)
        written.append((rgb, T, K))
    split = read_split(tmp_path, "test")
    assert [f.name for f in split.frames] == ["f0", "f1", "f2"]
    for frame, (rgb, T, K) in zip(split.frames, written):
        np.testing.assert_array_equal(frame.load_rgb(), rgb)  # PNG: lossless, RGB order kept
        np.testing.assert_allclose(frame.pose, T, rtol=1e-9, atol=1e-9)  # 10 significant digits on disk
        np.testing.assert_allclose(frame.intrinsics.K, K, rtol=1e-12)
        assert (frame.intrinsics.width, frame.intrinsics.height) == (W, H)
        assert frame.depth_path is None
        with pytest.raises(InputError, match="no depth"):
            frame.load_depth()


def test_depth_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.1, 60.0, size=(H, W)).astype(np.float32)
    depth[0, :5] = 0.0  # no depth
    rgb = np.zeros((H, W, 3), dtype=np.uint8)
    write_frame(tmp_path / "train", "d0", rgb, np.eye(4), np.diag([30.0, 30.0, 1.0]), depth=depth)
    frame = read_split(tmp_path).frames[0]
    back = frame.load_depth()
    assert back.dtype == np.float32 and back.shape == (H, W)
    np.testing.assert_allclose(back, depth, atol=0.0005 + 1e-6)  # stored in whole millimetres
    assert np.all(back[0, :5] == 0.0)
    np.testing.assert_array_equal(read_depth(frame.depth_path), back)


def test_written_files_have_default_permissions(tmp_path: Path) -> None:
    write_frame(tmp_path / "train", "p0", np.zeros((H, W, 3), np.uint8), np.eye(4), np.eye(3) * 5)
    for f in (tmp_path / "train").rglob("*.*"):
        assert f.stat().st_mode & 0o044, f  # group/other can read (not mkstemp's private 0600)


# ---------------------------------------------------------------- folders and counts


def test_missing_scene_folder(tmp_path: Path) -> None:
    expect_error(tmp_path / "nope", tmp_path / "nope", "does not exist")


def test_missing_split(tmp_path: Path) -> None:
    make_split(tmp_path, "train")
    expect_error(tmp_path, tmp_path / "test", "no 'test' split", split="test")


@pytest.mark.parametrize("sub", ["rgb", "poses", "calibration"])
def test_missing_subfolder(tmp_path: Path, sub: str) -> None:
    base = make_split(tmp_path)
    for f in (base / sub).iterdir():
        f.unlink()
    (base / sub).rmdir()
    expect_error(tmp_path, base / sub, "missing folder")


def test_empty_split(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=0)
    expect_error(tmp_path, base / "rgb", "empty")


@pytest.mark.parametrize("sub", ["poses", "calibration"])
def test_count_mismatch(tmp_path: Path, sub: str) -> None:
    base = make_split(tmp_path, n=3)
    (base / sub / "frame002.txt").unlink()
    expect_error(tmp_path, base / sub, "2 files but 3 images")


def test_count_mismatch_extra_file(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=2)
    (base / "poses" / "frame009.txt").write_text(pose_text(np.eye(4)))
    expect_error(tmp_path, base / "poses", "3 files but 2 images")


def test_depth_count_mismatch(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=2)
    (base / "depth").mkdir()
    cv2.imwrite(str(base / "depth" / "frame000.png"), np.zeros((H, W), np.uint16))
    expect_error(tmp_path, base / "depth", "1 depth maps but 2 images")


# ---------------------------------------------------------------- poses


def bad_pose(tmp_path: Path, text: str, *words: str) -> None:
    base = make_split(tmp_path, n=2)
    path = base / "poses" / "frame001.txt"
    path.write_text(text)
    expect_error(tmp_path, path, *words)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_non_finite_pose(tmp_path: Path, value: str) -> None:
    T = np.eye(4).astype(object)
    T[1, 3] = value
    bad_pose(tmp_path, "\n".join(" ".join(str(v) for v in row) for row in T), "non-finite")


def test_scaled_rotation_rejected(tmp_path: Path) -> None:
    bad_pose(tmp_path, pose_text(make_pose(1.01 * quat_to_matrix(np.array([1.0, 2, 3, 4])), [0, 0, 0])), "orthonormal")


def test_reflection_rejected(tmp_path: Path) -> None:
    bad_pose(tmp_path, pose_text(np.diag([1.0, 1.0, -1.0, 1.0])), "determinant")


def test_shear_rejected(tmp_path: Path) -> None:
    T = np.eye(4)
    T[0, 1] = 0.01
    bad_pose(tmp_path, pose_text(T), "orthonormal")


def test_pose_just_outside_tolerance_rejected(tmp_path: Path) -> None:
    T = np.eye(4)
    T[0, 0] = 1 + 0.51 * RIGID_TOL
    bad_pose(tmp_path, pose_text(T), "orthonormal")


def test_bad_last_row_rejected(tmp_path: Path) -> None:
    T = np.eye(4)
    T[3, 2] = 0.5
    bad_pose(tmp_path, pose_text(T), "last row")


def test_malformed_pose_numbers(tmp_path: Path) -> None:
    bad_pose(tmp_path, "1 0 0 0\n0 1 0 0\n0 0 one 0\n0 0 0 1\n", "cannot parse")


def test_ragged_pose_rows(tmp_path: Path) -> None:
    bad_pose(tmp_path, "1 0 0 0\n0 1 0\n0 0 1 0\n0 0 0 1\n", "cannot parse")


def test_pose_with_wrong_count(tmp_path: Path) -> None:
    bad_pose(tmp_path, "1 0 0 0\n0 1 0 0\n0 0 1 0\n", "16 numbers", "found 12")


def test_empty_pose_file(tmp_path: Path) -> None:
    with pytest.warns(UserWarning):  # numpy warns about an empty input file
        bad_pose(tmp_path, "", "found 0")


# ---------------------------------------------------------------- calibration


def bad_calib(tmp_path: Path, text: str, *words: str) -> None:
    base = make_split(tmp_path, n=2)
    path = base / "calibration" / "frame001.txt"
    path.write_text(text)
    expect_error(tmp_path, path, *words)


@pytest.mark.parametrize("text", ["0\n", "-525\n"])
def test_single_focal_not_positive(tmp_path: Path, text: str) -> None:
    bad_calib(tmp_path, text, "focal length must be positive")


@pytest.mark.parametrize("fx, fy", [(0.0, 50.0), (50.0, -50.0)])
def test_K_focal_not_positive(tmp_path: Path, fx: float, fy: float) -> None:
    bad_calib(tmp_path, f"{fx} 0 20\n0 {fy} 15\n0 0 1\n", "focal length must be positive")


def test_calibration_non_finite(tmp_path: Path) -> None:
    bad_calib(tmp_path, "50 0 nan\n0 50 15\n0 0 1\n", "non-finite")


def test_calibration_malformed(tmp_path: Path) -> None:
    bad_calib(tmp_path, "fifty\n", "cannot parse")


def test_calibration_wrong_count(tmp_path: Path) -> None:
    bad_calib(tmp_path, "50 50\n", "1 number", "found 2")


# ---------------------------------------------------------------- images


def test_corrupt_png(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=2)
    path = base / "rgb" / "frame001.png"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, size=2000, dtype=np.uint8).tobytes())
    expect_error(tmp_path, path, "cannot decode")


def test_truncated_jpeg(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=2, ext=".jpg")
    path = base / "rgb" / "frame001.jpg"
    data = path.read_bytes()
    assert data[:2] == b"\xff\xd8"
    path.write_bytes(data[: len(data) // 2])
    expect_error(tmp_path, path, "cannot decode")


def test_truncated_png(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=2)
    path = base / "rgb" / "frame000.png"
    path.write_bytes(path.read_bytes()[:-30])
    expect_error(tmp_path, path, "cannot decode")


def test_empty_image_file(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=2)
    path = base / "rgb" / "frame000.png"
    path.write_bytes(b"")
    expect_error(tmp_path, path, "cannot decode")


def test_read_rgb_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError) as info:
        read_rgb(tmp_path / "gone.png")
    assert str(info.value).startswith(str(tmp_path / "gone.png"))


def test_grayscale_image_becomes_rgb(tmp_path: Path) -> None:
    base = make_split(tmp_path, n=1)
    gray = np.arange(W * H, dtype=np.uint8).reshape(H, W)
    cv2.imwrite(str(base / "rgb" / "frame000.png"), gray)
    rgb = read_split(tmp_path).frames[0].load_rgb()
    assert rgb.shape == (H, W, 3)
    np.testing.assert_array_equal(rgb[..., 0], gray)
