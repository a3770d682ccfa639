"""Stage 1 mapping signals on a tiny synthetic scene: triangulated targets and their placement under augmentation."""

from __future__ import annotations

import numpy as np
import pytest

from acesplat.core.scene import read_split
from acesplat.scr.augment import augment
from acesplat.scr.mapping import cell_targets
from acesplat.scr.targets import triangulate_targets
from acesplat.synth import synthesize

SIZE = (96, 128)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scr") / "scene"
    synthesize(out, seed=3, train_frames=60, test_frames=12, size=SIZE, supersample=1)
    return out


def test_triangulated_targets_lie_on_the_true_surface(tiny_scene) -> None:
    train = read_split(tiny_scene, "train")
    frames = train.frames[:12]
    grays = [f.load_rgb().mean(axis=2).astype(np.uint8) for f in frames]
    targets = triangulate_targets(grays, [f.intrinsics for f in frames], [f.pose for f in frames])
    depth_err = []
    for f, t in zip(frames, targets):
        d = f.load_depth()
        px = np.round(t.pixels).astype(int)
        depth_err += list(np.abs(d[px[:, 1], px[:, 0]] - t.depths))
    assert len(depth_err) > 50
    assert np.median(depth_err) < 0.05  # metres, against rendered depth


def test_cell_targets_follow_the_augmentation(tiny_scene) -> None:
    from acesplat.scr.mapping import TrainingImage
    from acesplat.scr.targets import ImageTargets

    f = read_split(tiny_scene, "train").frames[0]
    depth = f.load_depth()
    ys, xs = np.mgrid[4 : SIZE[0] : 16, 4 : SIZE[1] : 16]
    px = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    z = depth[ys.ravel(), xs.ravel()].astype(np.float64)
    X = f.intrinsics.unproject(px, z) @ f.pose[:3, :3].T + f.pose[:3, 3]
    im = TrainingImage(f.load_rgb().mean(axis=2).astype(np.uint8), f.intrinsics, f.pose, ImageTargets(px, X, z))
    view = augment(im.gray, im.intrinsics, im.c2w, np.random.default_rng(0))
    gh, gw = view.cell_valid.shape
    tg = cell_targets(im, view, (gh, gw))
    has = np.isfinite(tg[:, 0])
    assert has.sum() > 10
    # Each target sits on its cell centre's ray in the augmented camera.
    from acesplat.core.geometry import invert_pose, transform_points
    from acesplat.core.grid import cell_centers

    uv = view.intrinsics.project(transform_points(invert_pose(view.c2w), tg[has]))
    np.testing.assert_allclose(uv, cell_centers(gh, gw)[has], atol=1e-3)


E2E_SIZE = (120, 160)
E2E_ITERATIONS = 1500
"""About 70 s on two idle cores in float32 (the suite's one end-to-end map; full-size runs live in bench/)."""
E2E_MIN_WITHIN = 11
"""Test frames of 12 that must land within E2E_WITHIN_M / E2E_WITHIN_DEG (measured 12 of 12, the worst 11.0 cm /
2.4 deg; dense 12 of 12, the worst 8.7 cm / 2.2 deg)."""
E2E_WITHIN_M, E2E_WITHIN_DEG = 0.15, 5.0


def test_tiny_scene_maps_and_localizes_most_test_frames(tmp_path) -> None:
    import torch

    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.localize import Localizer, evaluate
    from acesplat.scr.mapping import MappingConfig, map_scene
    from acesplat.scr.network import SCRNetwork

    scene = tmp_path / "scene"
    synthesize(scene, seed=3, train_frames=60, test_frames=12, size=E2E_SIZE, supersample=1)
    enc, _ = load_encoder(None)  # the shipped encoder: what a user maps with
    cfg = MappingConfig(
        iterations=E2E_ITERATIONS,
        short_side=E2E_SIZE[0],
        batch_size=1024,
        buffer_size=60_000,
        samples_per_image=512,
        precision="fp32",
    )
    torch.manual_seed(0)
    res = map_scene(read_split(scene, "train"), enc, cfg)
    assert res.iterations == E2E_ITERATIONS and res.target_features > 1000
    s = evaluate(read_split(scene, "test"), Localizer(SCRNetwork(enc, res.head).eval(), E2E_SIZE[0], {}))
    within = [
        f
        for f in s["per_frame"]
        if f["localized"] and f["translation_m"] < E2E_WITHIN_M and f["rotation_deg"] < E2E_WITHIN_DEG
    ]
    assert len(within) >= E2E_MIN_WITHIN, s["per_frame"]
    assert s["median_translation_m"] < 0.08  # measured 5.4 cm
    # The dense prediction (every 4th pixel) runs the same map and must localize most test frames too.
    dense = Localizer(SCRNetwork(enc, res.head).eval(), E2E_SIZE[0], {}, output_stride=4)
    d = evaluate(read_split(scene, "test"), dense)
    within_dense = [
        f
        for f in d["per_frame"]
        if f["localized"] and f["translation_m"] < E2E_WITHIN_M and f["rotation_deg"] < E2E_WITHIN_DEG
    ]
    assert len(within_dense) >= E2E_MIN_WITHIN, d["per_frame"]
    assert d["median_translation_m"] < 0.08  # measured 4.7 cm
    # Refined against the nearest training images (warped with this map's own depth), poses get better.
    from acesplat.scr.keyframes import MapKeyframes

    net = SCRNetwork(enc, res.head).eval()
    keyframes = MapKeyframes(read_split(scene, "train"), net, E2E_SIZE[0])
    a = evaluate(read_split(scene, "test"), Localizer(net, E2E_SIZE[0], {}, keyframes=keyframes))
    assert a["keyframe_alignment"].get("aligned", 0) >= E2E_MIN_WITHIN, a["keyframe_alignment"]  # measured 12
    assert a["median_translation_m"] < 0.015, a["per_frame"]  # measured 0.55 cm (5.4 cm before alignment)


def test_map_command_rejects_a_bad_precision(tmp_path) -> None:
    from typer.testing import CliRunner

    from acesplat.apps.cli import app

    res = CliRunner().invoke(app, ["map", str(tmp_path), "-o", str(tmp_path / "m.pt"), "--precision", "fp64"])
    assert res.exit_code == 2, res.output
    assert res.stderr.count("\n") == 1 and "--precision must be auto, fp32 or bf16, got 'fp64'" in res.stderr
    assert not (tmp_path / "m.pt").exists()


def test_bf16_buffer_features_match_fp32_and_leave_the_encoder_as_it_was(tiny_scene) -> None:
    import time

    import torch

    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.mapping import MappingConfig, fill_buffer, load_training_images

    images = load_training_images(read_split(tiny_scene, "train"), SIZE[0])[:4]
    enc, _ = load_encoder(None)
    bufs = {}
    for precision in ("fp32", "bf16"):
        cfg = MappingConfig(short_side=SIZE[0], buffer_size=400, samples_per_image=100, precision=precision)
        bufs[precision] = fill_buffer(images, enc, cfg, time.monotonic() + 60, np.random.default_rng(0))
        assert all(p.is_contiguous() for p in enc.parameters())  # localization sees the usual layout
    a, b = bufs["fp32"]["feats"].float(), bufs["bf16"]["feats"].float()
    assert a.shape == b.shape == (400, enc.cfg.out)
    assert torch.equal(bufs["fp32"]["pixels"], bufs["bf16"]["pixels"])  # same views and cells, other arithmetic
    rel = float((a - b).norm() / a.norm())
    assert 0 < rel < 0.02, rel  # bfloat16 keeps ~3 significant digits


def test_map_command_rejects_an_unknown_augmentation(tmp_path) -> None:
    from typer.testing import CliRunner

    from acesplat.apps.cli import app

    res = CliRunner().invoke(app, ["map", str(tmp_path), "-o", str(tmp_path / "m.pt"), "--augment", "flip"])
    assert res.exit_code == 2, res.output
    assert res.stderr.count("\n") == 1 and "--augment must be one of ace, photometric, got 'flip'" in res.stderr
    assert not (tmp_path / "m.pt").exists()


def test_target_term_is_the_clamped_distance_in_pixels_at_the_targets_depth() -> None:
    import torch

    from acesplat.scr.mapping import TARGET_CLAMP_M, TARGET_WEIGHT_PX, target_term

    # Two targets seen by a camera at the origin looking down +z (w2c = [I | 0]), f = 200 px:
    # one at 2 m missed by 3 cm, one at 4 m missed by 5 m (clamped).
    w2c = torch.zeros(2, 3, 4)
    w2c[:, :, :3] = torch.eye(3)
    K = torch.tensor([[200.0, 0, 64], [0, 200, 48], [0, 0, 1]]).repeat(2, 1, 1)
    target = torch.tensor([[0.1, 0.0, 2.0], [0.0, -0.2, 4.0]])
    pred = target + torch.tensor([[0.0, 0.03, 0.0], [5.0, 0.0, 0.0]])
    expected = TARGET_WEIGHT_PX * (0.03 * 200 / 2.0 + TARGET_CLAMP_M * 200 / 4.0)
    assert float(target_term(pred, target, w2c, K)) == pytest.approx(expected, rel=1e-5)


def test_buffer_restores_the_encoder_layout_when_the_loop_raises(tiny_scene) -> None:
    import time

    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.mapping import MappingConfig, fill_buffer, load_training_images

    images = load_training_images(read_split(tiny_scene, "train"), SIZE[0])[:2]
    enc, _ = load_encoder(None)

    def interrupted(*_):
        raise KeyboardInterrupt

    cfg = MappingConfig(short_side=SIZE[0], buffer_size=400, samples_per_image=100, precision="bf16")
    with pytest.raises(KeyboardInterrupt):
        fill_buffer(images, enc, cfg, time.monotonic() + 60, np.random.default_rng(0), interrupted)
    assert all(p.is_contiguous() for p in enc.parameters())


def test_eval_command_dense_reports_its_output_stride(tiny_scene, tmp_path) -> None:
    import json

    import torch
    from typer.testing import CliRunner

    from acesplat.apps.cli import app
    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.mapfile import SceneMap, save_map
    from acesplat.scr.network import Encoder, EncoderConfig, Head, HeadConfig

    torch.manual_seed(0)
    enc_path = tmp_path / "enc.pt"
    torch.save(Encoder(EncoderConfig(4, 8, 8, 16, 16, 32)).state_dict(), enc_path)
    _, ident = load_encoder(enc_path)
    mean = np.mean([f.pose[:3, 3] for f in read_split(tiny_scene, "train").frames], axis=0)
    save_map(
        tmp_path / "m.pt", SceneMap(Head(torch.from_numpy(mean).float(), 32, HeadConfig(16, 1)), ident, mean, SIZE[0])
    )
    for flag, stride in (([], 8), (["--dense"], 4), (["--align"], 8)):
        out = tmp_path / f"eval{stride}{flag}.json"
        res = CliRunner().invoke(app, ["eval", str(tmp_path / "m.pt"), str(tiny_scene), "--json", str(out), *flag])
        assert res.exit_code == 0, res.output
        report = json.loads(out.read_text())
        assert report["output_stride"] == stride and report["frames"] == 12 and len(report["per_frame"]) == 12
        assert report["aligned_to_keyframes"] == (flag == ["--align"])
        # an untrained head localizes nothing, so no alignment is tried; the count says so
        assert ("keyframe_alignment" in report) == (flag == ["--align"])


def test_novel_views_join_the_buffer_late_and_the_run_keeps_its_iteration_count(tiny_scene) -> None:
    import torch

    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.mapping import MappingConfig, map_scene

    enc, _ = load_encoder(None)
    cfg = MappingConfig(
        iterations=40,
        short_side=SIZE[0],
        batch_size=256,
        buffer_size=4000,
        samples_per_image=200,
        precision="fp32",
        novel_views=6,
    )
    torch.manual_seed(0)
    res = map_scene(read_split(tiny_scene, "train"), enc, cfg)
    assert res.iterations == 40 and res.buffer_features == 4000
    assert res.novel_view_features > 6 * 20  # a 96x128 view has 192 cells; most survive the warp
    assert all(p.is_contiguous() for p in enc.parameters())  # the encoder's layout is back


def test_map_command_rejects_a_negative_novel_view_count(tmp_path) -> None:
    from typer.testing import CliRunner

    from acesplat.apps.cli import app

    r = CliRunner().invoke(app, ["map", str(tmp_path), "-o", str(tmp_path / "m.pt"), "--novel-views", "-1"])
    assert r.exit_code == 2 and "--novel-views" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "m.pt").exists()
