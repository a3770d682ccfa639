"""`acesplat pose` (pycolmap structure from motion) on a few built-in-scene images, and its bad inputs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.apps.cli import app
from acesplat.core.errors import InputError
from acesplat.core.geometry import apply_similarity, pose_error, rotation_angle_deg, similarity_align
from acesplat.core.scene import read_split, write_capture
from acesplat.importers.sfm import METADATA_FILE, PoseConfig, pose_images

pytest.importorskip("pycolmap")

FRAMES = range(10, 50, 4)
"""Ten frames of the built-in scene's 200-frame training pass: a turn and a straight stretch (1.8 m)."""
POS_TOL = 0.006
"""Largest position error after the similarity alignment, as a fraction of the trajectory length
(measured 0.33%, bench/pose.md)."""
REL_ROT_TOL_DEG = 0.25
"""Largest error of the rotation between consecutive frames (gauge-free)."""
SCALE_TOL = 0.01
"""Metric scale from --scale-from within 1%."""

runner = CliRunner()


@pytest.fixture(scope="module")
def room_images(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """The ten frames as plain PNGs (f00.png ...) plus a noise image pycolmap cannot register, and the true poses."""
    from acesplat.synth.dataset import default_intrinsics, texel_density_for
    from acesplat.synth.render import render_view
    from acesplat.synth.room import make_room
    from acesplat.synth.trajectory import TRAIN_PASS, make_trajectory

    root = tmp_path_factory.mktemp("pose")
    K = default_intrinsics((240, 320))
    scene = make_room(0, texel_density=texel_density_for(K))
    poses = make_trajectory(scene.path, 200, **TRAIN_PASS)[list(FRAMES)]
    for i, T in enumerate(poses):
        rgb, _ = render_view(scene, T, K, supersample=1)
        write_capture(root, f"f{i:02d}", rgb)
    noise = np.random.default_rng(0).integers(0, 256, size=(240, 320, 3), dtype=np.uint8)
    write_capture(root, "zz_noise", cv2.GaussianBlur(noise, (0, 0), 2.0))
    return root / "rgb", poses


def _cli(*args: str):
    return runner.invoke(app, ["pose", *map(str, args)])


def _scene_poses(scene: Path) -> tuple[list[int], np.ndarray]:
    """Indices (from the f<NN> names) and poses of every frame of both splits."""
    frames = read_split(scene, "train").frames + (
        read_split(scene, "test").frames if (scene / "test" / "rgb").is_dir() else []
    )
    return [int(f.name.rsplit("_f", 1)[1]) for f in frames], np.stack([f.pose for f in frames])


def test_pose_recovers_the_true_trajectory_in_metres(room_images, tmp_path: Path) -> None:
    images, truth = room_images
    gap = float(np.linalg.norm(truth[0, :3, 3] - truth[-1, :3, 3]))
    scene = tmp_path / "scene"
    r = _cli(images, "-o", scene, "--scale-from", "f00.png", "f09.png", f"{gap:.9f}", "--test-every", "4",
             "--json", tmp_path / "pose.json")  # fmt: skip
    assert r.exit_code == 0, r.output
    report = json.loads((tmp_path / "pose.json").read_text())
    assert report["images"] == 11 and report["registered"] == 10
    assert report["unregistered"] == ["zz_noise.png"] and report["unregistered_count"] == 1
    assert report["units"] == "metres" and report["points"] > 100
    assert 0 < report["mean_reprojection_error_px"] < 1.0
    assert (report["train"], report["test"]) == (7, 3)
    assert json.loads((scene / METADATA_FILE).read_text())["units"] == "metres"
    idx, est = _scene_poses(scene)
    gt = truth[idx]
    s, R, t = similarity_align(est[:, :3, 3], gt[:, :3, 3])
    assert abs(s - 1.0) < SCALE_TOL
    aligned = apply_similarity(s, R, t, est)
    length = float(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum())
    worst = max(pose_error(a, g)[0] for a, g in zip(aligned, gt))
    assert worst < POS_TOL * length, (worst, length)
    order = np.argsort(idx)
    for i, j in zip(order[:-1], order[1:]):
        rel_est = est[i, :3, :3].T @ est[j, :3, :3]
        rel_gt = gt[i, :3, :3].T @ gt[j, :3, :3]
        assert rotation_angle_deg(rel_est.T @ rel_gt) < REL_ROT_TOL_DEG


def test_pose_keeps_arbitrary_units_and_says_so(room_images, tmp_path: Path) -> None:
    """Four frames, exhaustive matching, no --scale-from: the scene's metadata says the units are COLMAP's."""
    images, _ = room_images
    few = tmp_path / "few"
    few.mkdir()
    for i in range(4):
        (few / f"f{i:02d}.png").symlink_to(images / f"f{i:02d}.png")
    summary = pose_images(few, tmp_path / "scene", PoseConfig(matcher="exhaustive"), test_every=0)
    assert summary.registered == 4 and summary.unregistered == [] and summary.scale == 1.0
    meta = json.loads((tmp_path / "scene" / METADATA_FILE).read_text())
    assert meta["units"] == "arbitrary" and meta["scale_from"] is None and meta["matcher"] == "exhaustive"


# ----------------------------------------------------------------------------------- bad input
def _assert_refused(r, *words: str) -> None:
    assert r.exit_code == 2, r.output
    lines = [line for line in r.output.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, r.output
    for w in words:
        assert w in lines[0], lines[0]


def _nothing_written(parent: Path, keep: set[str]) -> None:
    assert {p.name for p in parent.iterdir()} == keep  # no scene, no staging folder left behind


def test_missing_and_empty_folders_are_refused(tmp_path: Path) -> None:
    _assert_refused(_cli(tmp_path / "nope", "-o", tmp_path / "scene"), "nope", "does not exist")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("not an image")
    _assert_refused(_cli(tmp_path / "empty", "-o", tmp_path / "scene"), "empty", "no images")
    _nothing_written(tmp_path, {"empty"})


def test_an_unreadable_image_is_named(tmp_path: Path) -> None:
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for i in range(3):
        cv2.imwrite(str(imgs / f"a{i}.png"), np.full((32, 32, 3), 100, np.uint8))
    (imgs / "a3.png").write_bytes(b"not a png at all")
    _assert_refused(_cli(imgs, "-o", tmp_path / "scene"), "a3.png", "cannot decode")
    _nothing_written(tmp_path, {"imgs"})


def test_images_pycolmap_cannot_register_are_refused_with_the_count(tmp_path: Path) -> None:
    """Featureless gradients: nothing registers; exit 2 saying how many did, and nothing is left behind."""
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    ramp = np.linspace(0, 255, 160, dtype=np.float64)[None, :, None] * np.ones((120, 1, 3))
    for i in range(4):
        cv2.imwrite(str(imgs / f"g{i}.png"), np.clip(ramp * (0.5 + 0.1 * i), 0, 255).astype(np.uint8))
    _assert_refused(_cli(imgs, "-o", tmp_path / "scene"), "registered 0 of 4", "at least 3")
    _nothing_written(tmp_path, {"imgs"})


def test_scale_from_and_output_checks_come_before_any_work(room_images, tmp_path: Path) -> None:
    images, _ = room_images
    out = tmp_path / "scene"
    _assert_refused(_cli(images, "-o", out, "--scale-from", "f00.png", "nope.png", "1.5"), "nope.png", "not one of")
    _assert_refused(_cli(images, "-o", out, "--scale-from", "f00.png", "f01.png", "-1"), "positive")
    _assert_refused(_cli(images, "-o", out, "--scale-from", "f00.png", "f00.png", "1"), "two different")
    out.mkdir()
    (out / "x").write_text("taken")
    _assert_refused(_cli(images, "-o", out), "scene", "not an empty folder")


def test_different_sizes_need_per_image_cameras(tmp_path: Path) -> None:
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    cv2.imwrite(str(imgs / "a.png"), np.zeros((32, 32, 3), np.uint8))
    cv2.imwrite(str(imgs / "b.png"), np.zeros((32, 48, 3), np.uint8))
    _assert_refused(_cli(imgs, "-o", tmp_path / "scene"), "b.png", "--per-image-camera")


def test_missing_pycolmap_is_one_line(tmp_path: Path, monkeypatch) -> None:
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    cv2.imwrite(str(imgs / "a.png"), np.zeros((32, 32, 3), np.uint8))
    monkeypatch.setitem(sys.modules, "pycolmap", None)
    with pytest.raises(InputError, match="pycolmap is not installed"):
        pose_images(imgs, tmp_path / "scene")
    _nothing_written(tmp_path, {"imgs"})
