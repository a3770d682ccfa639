"""Frame sources and their geometry: calibration files, OAK resize modes, undistortion, replay pacing (the OAK
source itself: tests/test_oak.py)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError
from edge.calibration import CameraCalibration, read_calibration_file
from edge.frame_prep import FramePrep, crop_to_aspect
from edge.oak import resize_intrinsics
from edge.sources import ReplaySource, SourceOptions, UnreadableFrame, open_source

K0 = np.array([[1500.0, 0, 955.3], [0, 1498.0, 541.7], [0, 0, 1]])


def _project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    return (X[:, :2] / X[:, 2:3]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]


@pytest.mark.parametrize("mode", ["crop", "stretch", "letterbox"])
def test_oak_resize_modes_map_sensor_pixels_exactly(mode: str) -> None:
    """Each mode's K must project a point where the device's resize moves its sensor pixel."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(2, 5, 20)]
    uv0 = _project(K0, X)  # sensor pixels, 1920 x 1080
    W0, H0, W, H = 1920, 1080, 640, 480
    intr = resize_intrinsics(K0, (W0, H0), (W, H), mode)
    if mode == "stretch":
        sx, sy, ox, oy = W / W0, H / H0, 0.0, 0.0
    elif mode == "crop":  # scale by the larger ratio, cut the overflowing width evenly
        sx = sy = 480 / 1080
        ox, oy = -(1920 * sx - 640) / 2, 0.0
    else:  # scale by the smaller ratio, pad the height evenly
        sx = sy = 640 / 1920
        ox, oy = 0.0, (480 - 1080 * sy) / 2
    expected = np.c_[(uv0[:, 0] + 0.5) * sx - 0.5 + ox, (uv0[:, 1] + 0.5) * sy - 0.5 + oy]
    np.testing.assert_allclose(_project(intr.K, X), expected, atol=1e-9)
    assert (intr.width, intr.height) == (640, 480)


def test_calibration_formats(tmp_path: Path) -> None:
    (tmp_path / "k.json").write_text(
        json.dumps(
            {
                "fx": 600,
                "fy": 601,
                "cx": 319.5,
                "cy": 239.5,
                "width": 640,
                "height": 480,
                "distortion": [0.1, -0.05, 0, 0, 0],
            }
        )
    )
    c = read_calibration_file(tmp_path / "k.json")
    assert c.intrinsics_for(320, 240) == Intrinsics(600, 601, 319.5, 239.5, 640, 480).resized(320, 240)
    assert c.has_distortion
    fs = cv2.FileStorage(str(tmp_path / "k.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.release()
    y = read_calibration_file(tmp_path / "k.yaml")
    assert y.size == (640, 480) and y.intrinsics_for(640, 480).fx == 600 and not y.has_distortion
    (tmp_path / "f.txt").write_text("500\n")
    assert read_calibration_file(tmp_path / "f.txt").intrinsics_for(100, 80) == Intrinsics(500, 500, 50, 40, 100, 80)
    with pytest.raises(InputError, match="different aspect ratio"):
        c.intrinsics_for(640, 360)
    (tmp_path / "bad.json").write_text(json.dumps({"fx": -1, "fy": 1, "cx": 0, "cy": 0}))
    with pytest.raises(InputError, match="positive focal"):
        read_calibration_file(tmp_path / "bad.json")
    (tmp_path / "k9.txt").write_text("600 0 900\n0 600 500\n0 0 1\n")
    with pytest.raises(InputError, match="outside the 640x480 frame"):
        read_calibration_file(tmp_path / "k9.txt").intrinsics_for(640, 480)


def test_undistortion_puts_points_where_the_pinhole_model_says() -> None:
    """Draw dots where a distorted camera sees them; after FramePrep they sit at the pinhole projections."""
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    dist = np.array([-0.25, 0.08, 0.001, -0.001, 0.0])
    gx, gy = np.meshgrid(np.linspace(-0.4, 0.4, 4), np.linspace(-0.28, 0.28, 3))
    X = np.c_[gx.ravel(), gy.ravel(), np.ones(12)]
    distorted, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist)
    img = np.zeros((240, 320), np.uint8)
    for u, v in distorted.reshape(-1, 2):
        cv2.circle(img, (int(round(u * 16)), int(round(v * 16))), 3 * 16, 255, -1, shift=4)
    gray, intr = FramePrep((240, 320))(img, Intrinsics.from_K(K, 320, 240), dist)
    ideal = _project(intr.K, X)
    n, _, stats, centroids = cv2.connectedComponentsWithStats((gray > 127).astype(np.uint8))
    assert n - 1 == len(X)
    for c in centroids[1:]:
        assert np.min(np.linalg.norm(ideal - c, axis=1)) < 0.35


def test_crop_to_aspect_shifts_the_principal_point() -> None:
    img = np.zeros((100, 200), np.uint8)
    out, intr = crop_to_aspect(img, Intrinsics(150, 150, 99.5, 49.5, 200, 100), 4 / 3)
    assert out.shape == (100, 133) and intr.cx == pytest.approx(99.5 - 33) and intr.width == 133


def test_replay_folder_of_images_with_timestamps_and_pacing(tmp_path: Path) -> None:
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((48, 64, 3), 40 * i, np.uint8))
    (tmp_path / "f9.png").write_bytes(b"not an image")
    (tmp_path / "intrinsics.txt").write_text("50\n")
    (tmp_path / "timestamps.txt").write_text("f0 10.0\nf1 10.5\nf2 11.0\nf9 11.5\n")
    now = {"t": 100.0}
    slept: list[float] = []

    def sleep(s: float) -> None:
        slept.append(s)
        now["t"] += s

    src = ReplaySource(tmp_path, realtime=True, clock=lambda: now["t"], sleep=sleep)
    frames = [src.read() for _ in range(3)]
    assert [f.name for f in frames] == ["f0", "f1", "f2"] and [f.timestamp for f in frames] == [10.0, 10.5, 11.0]
    assert slept == pytest.approx([0.5, 0.5]) and src.live
    assert frames[1].intrinsics == Intrinsics.from_focal(50, 64, 48)
    with pytest.raises(UnreadableFrame, match="f9.png"):
        src.read()
    assert src.read() is None
    (tmp_path / "timestamps.txt").unlink()
    with pytest.raises(InputError, match="recorded timestamps"):
        ReplaySource(tmp_path, realtime=True)
    with pytest.raises(InputError, match="no images"):
        ReplaySource(tmp_path / "empty" if (tmp_path / "empty").mkdir() is None else tmp_path)


def test_camera_that_is_absent_at_start_is_bad_input() -> None:
    class Closed:
        def isOpened(self) -> bool:  # noqa: N802
            return False

        def release(self) -> None: ...

    from edge.sources import CameraSource

    with pytest.raises(InputError, match="camera 7 cannot be opened"):
        CameraSource(7, CameraCalibration(focal=100.0), opener=lambda i: Closed())


def test_video_source_gives_container_timestamps_and_rescaled_intrinsics(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (80, 64))
    if not w.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG/AVI")
    for i in range(4):
        w.write(np.full((64, 80, 3), 50 * i, np.uint8))
    w.release()
    calib = CameraCalibration(K=np.array([[100.0, 0, 79.5], [0, 100.0, 63.5], [0, 0, 1]]), size=(160, 128))
    src = open_source(f"video:{path}", SourceOptions(calibration=calib))
    frames = []
    while (f := src.read()) is not None:
        frames.append(f)
    src.close()
    assert [f.frame_id for f in frames] == [0, 1, 2, 3]
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 0.1, 0.2, 0.3])
    assert frames[0].intrinsics == calib.intrinsics_for(80, 64) and frames[0].intrinsics.fx == 50.0
    with pytest.raises(InputError, match="needs --intrinsics"):
        open_source(f"video:{path}", SourceOptions())
