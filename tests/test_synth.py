"""The built-in synthetic scene: primitives against analytic and brute-force references, exact z-depth,
multi-view consistency, determinism, separate test pass, ACE layout round trip, texture richness, bad inputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.apps.cli import app
from acesplat.core.errors import InputError
from acesplat.core.geometry import invert_pose, look_at, rigidity_problem, transform_points
from acesplat.core.scene import read_split
from acesplat.synth import (
    TEST_PASS,
    TRAIN_PASS,
    default_intrinsics,
    make_room,
    make_trajectory,
    random_scene_frames,
    render_view,
    synthesize,
)
from acesplat.synth.atlas import build_atlas, sample
from acesplat.synth.dataset import texel_density_for
from acesplat.synth.layout import CAMERA_CLEARANCE
from acesplat.synth.primitives import (
    MISS,
    exit_room,
    hit_box,
    hit_cylinder,
    hit_sphere,
    sdf_box,
    sdf_box_xy,
    sdf_cylinder,
    sdf_sphere,
)
from acesplat.synth.render import cast, pixel_rays

TINY = (48, 64)
SMALL = (96, 128)


def _ray(o, d):
    o = np.asarray(o, np.float32)
    d = np.asarray(d, np.float32).reshape(-1, 3)
    return (o[0], o[1], o[2], d[:, 0].copy(), d[:, 1].copy(), d[:, 2].copy())


@pytest.fixture(scope="module")
def small_room():
    K = default_intrinsics(SMALL)
    return make_room(0, texel_density=texel_density_for(K)), K


# ---------------------------------------------------------------- primitives


def test_box_hits_match_hand_computed_distances() -> None:
    c, h = np.array([5.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0])
    assert hit_box(*_ray([0, 0, 0], [1, 0, 0]), c, h, 0.0)[0] == pytest.approx(4.0, abs=1e-5)
    # Rotated by 45 degrees the box shows an edge to the ray: entry at 5 - sqrt(2).
    assert hit_box(*_ray([0, 0, 0], [1, 0, 0]), c, h, np.pi / 4)[0] == pytest.approx(5 - np.sqrt(2), abs=1e-5)
    # Unnormalised directions scale t inversely (the renderer relies on it for z-depth).
    assert hit_box(*_ray([0, 0, 0], [2, 0, 0]), c, h, 0.0)[0] == pytest.approx(2.0, abs=1e-5)
    assert hit_box(*_ray([0, 0, 0], [0, 1, 0]), c, h, 0.0)[0] == MISS
    assert hit_box(*_ray([0, 0, 0], [-1, 0, 0]), c, h, 0.0)[0] == MISS  # behind
    assert hit_box(*_ray([5, 0, 0], [1, 0, 0]), c, h, 0.0)[0] == MISS  # starts inside


def test_cylinder_and_sphere_hits_match_hand_computed_distances() -> None:
    cyl = (np.array([3.0, 0.0]), 1.0, -1.0, 1.0)
    assert hit_cylinder(*_ray([0, 0, 0], [1, 0, 0]), *cyl)[0] == pytest.approx(2.0, abs=1e-5)
    assert hit_cylinder(*_ray([3, 0, 5], [0, 0, -1]), *cyl)[0] == pytest.approx(4.0, abs=1e-5)  # top cap
    assert hit_cylinder(*_ray([3, 0.5, -4], [0, 0, 1]), *cyl)[0] == pytest.approx(3.0, abs=1e-5)  # bottom cap
    assert hit_cylinder(*_ray([0, 0, 2], [1, 0, 0]), *cyl)[0] == MISS  # passes over the top
    assert hit_sphere(*_ray([0, 0, 0], [0, 0, 1]), np.array([0.0, 0.0, 5.0]), 1.0)[0] == pytest.approx(4.0, abs=1e-5)
    assert hit_sphere(*_ray([0, 1.01, 0], [0, 0, 1]), np.array([0.0, 0.0, 5.0]), 1.0)[0] == MISS


def test_hits_agree_with_brute_force_marching_along_the_ray() -> None:
    """The returned t lies on the surface (sdf ~ 0) and no point before it is inside the object."""
    rng = np.random.default_rng(4)
    prims = [
        (lambda *r: hit_box(*r, np.array([0.3, -0.2, 0.1]), np.array([0.5, 0.3, 0.4]), 0.7),
         lambda X: sdf_box(X, np.array([0.3, -0.2, 0.1]), np.array([0.5, 0.3, 0.4]), 0.7)),
        (lambda *r: hit_cylinder(*r, np.array([0.1, 0.2]), 0.4, -0.3, 0.5),
         lambda X: sdf_cylinder(X, np.array([0.1, 0.2]), 0.4, -0.3, 0.5)),
        (lambda *r: hit_sphere(*r, np.array([-0.1, 0.0, 0.2]), 0.45),
         lambda X: sdf_sphere(X, np.array([-0.1, 0.0, 0.2]), 0.45)),
    ]  # fmt: skip
    for hit, sdf in prims:
        o = rng.normal(size=3) * 0.3 + np.array([0.0, 0.0, 2.5])
        targets = rng.uniform(-0.8, 0.8, size=(400, 3))
        d = (targets - o).astype(np.float32)
        t = hit(*_ray(o, d)).astype(np.float64)
        hits = t < MISS
        assert hits.mean() > 0.2
        X = o + t[hits, None] * d[hits]
        assert np.abs(sdf(X)).max() < 2e-3
        steps = np.linspace(0.0, 1.0, 200)[:-1]
        before = o + (t[hits, None, None] * steps[None, :, None]) * d[hits, None, :]
        assert sdf(before).min() > -2e-3
        # Misses: no point of the marched segment is inside.
        far = o + np.linspace(0.0, 3.0, 300)[None, :, None] * d[~hits, None, :]
        assert sdf(far).min() > -2e-3


def test_room_exit_lands_on_the_boundary() -> None:
    rng = np.random.default_rng(1)
    size = np.array([6.0, 4.0, 3.0])
    o = np.array([1.5, 2.5, 1.2], np.float32)
    d = rng.normal(size=(500, 3)).astype(np.float32)
    d[0] = [1, 0, 0]  # axis-aligned rays have zero components
    ts, _ = exit_room(*_ray(o, d), size)
    t = np.minimum(np.minimum(ts[0], ts[1]), ts[2])
    X = o + t[:, None] * d
    assert np.all(X > -1e-4) and np.all(X < size + 1e-4)
    assert np.abs(np.minimum(X, size - X)).min(axis=1).max() < 1e-4
    assert t[0] == pytest.approx(4.5)


# ---------------------------------------------------------------- texture atlas


def test_atlas_sampling_is_exact_at_texel_centres_and_wraps() -> None:
    ramp = np.zeros((4, 8, 3), np.float32)
    ramp[..., 0] = np.arange(8)[None] / 7.0
    flat = np.full((6, 6, 3), 0.5, np.float32)
    atlas = build_atlas([ramp, flat, ramp], wrap_u=[False, False, True])
    u = (np.arange(8) + 0.5) / 8
    got = sample(atlas, np.zeros(8, int), u, np.full(8, 0.5), np.zeros(8))
    np.testing.assert_allclose(got[:, 0], np.round(np.arange(8) / 7.0 * 255), atol=0.6)
    const = sample(atlas, np.ones(5, int), np.linspace(0, 1, 5), np.linspace(0, 1, 5), np.linspace(0, 5, 5))
    np.testing.assert_allclose(const, 128.0, atol=0.6)
    # u = 0 sits between the last and the first texel: the average when wrapping, the edge when clamping.
    wrap = sample(atlas, np.array([2]), np.array([0.0]), np.array([0.5]), np.array([0.0]))
    clamp = sample(atlas, np.array([0]), np.array([0.0]), np.array([0.5]), np.array([0.0]))
    assert wrap[0, 0] == pytest.approx(255 / 2, abs=1.0)
    assert clamp[0, 0] == pytest.approx(0.0, abs=0.6)
    # A coarser level is the box-filtered texture: the mean of the ramp.
    coarse = sample(atlas, np.array([0]), np.array([0.5]), np.array([0.5]), np.array([10.0]))
    assert coarse[0, 0] == pytest.approx(255 / 2, abs=3.0)


# ---------------------------------------------------------------- rendering


def test_depth_is_metric_z_depth_on_a_fronto_parallel_wall() -> None:
    """An empty room seen square-on: every wall pixel has the same z-depth, the distance to the wall."""
    scene = make_room(2, n_objects=0, texel_density=30.0)
    assert len(scene.objects) == 0
    K = default_intrinsics(TINY)
    eye = np.array([2.0, 2.0, 1.5])
    _, depth = render_view(scene, look_at(eye, eye + [1.0, 0.0, 0.0]), K)
    assert depth.dtype == np.float32 and depth.shape == TINY
    assert depth[TINY[0] // 2, TINY[1] // 2] == pytest.approx(4.0, abs=1e-5)
    # Depth is z, not range: unprojected points land exactly on the planes of the room.
    uv = np.stack(np.meshgrid(np.arange(TINY[1]), np.arange(TINY[0])), -1).reshape(-1, 2).astype(float)
    X = transform_points(look_at(eye, eye + [1.0, 0.0, 0.0]), K.unproject(uv, depth.reshape(-1).astype(float)))
    dist = np.minimum(X, scene.size - X).min(axis=1)
    assert np.abs(dist).max() < 1e-4


def test_views_are_geometrically_and_photometrically_consistent(small_room) -> None:
    """Unproject view A with its depth, reproject into view B: where visible, depth and colour agree."""
    scene, K = small_room
    train = make_trajectory(scene.path, 200, **TRAIN_PASS)
    test = make_trajectory(scene.path, 60, **TEST_PASS)
    nearest = int(np.argmin(np.linalg.norm(train[:, :3, 3] - test[20, :3, 3], axis=1)))
    checked = 0
    for pose_a, pose_b in ((train[0], train[3]), (train[120], train[124]), (test[20], train[nearest])):
        rgb_a, depth_a = render_view(scene, pose_a, K)
        rgb_b, depth_b = render_view(scene, pose_b, K)
        uv = np.stack(np.meshgrid(np.arange(K.width), np.arange(K.height)), -1).reshape(-1, 2).astype(float)
        Xw = transform_points(pose_a, K.unproject(uv, depth_a.reshape(-1).astype(float)))
        Xb = transform_points(invert_pose(pose_b), Xw)
        pb = K.project(Xb)
        u0, v0 = np.floor(pb[:, 0]).astype(int), np.floor(pb[:, 1]).astype(int)
        inside = (Xb[:, 2] > 0.1) & (u0 >= 0) & (u0 < K.width - 1) & (v0 >= 0) & (v0 < K.height - 1)
        u0, v0, fu, fv, zt = (
            u0[inside],
            v0[inside],
            pb[inside, 0] - u0[inside],
            pb[inside, 1] - v0[inside],
            Xb[inside, 2],
        )
        quad = np.stack([depth_b[v0, u0], depth_b[v0, u0 + 1], depth_b[v0 + 1, u0], depth_b[v0 + 1, u0 + 1]], 1)
        # Inverse depth is bilinear in the image on a plane: interpolate it among four neighbours on one surface.
        smooth = quad.max(1) < 1.02 * quad.min(1)
        w = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], 1)
        zb = 1.0 / (w / quad).sum(1)
        visible = smooth & (np.abs(zb - zt) < 0.01 * zt)
        assert smooth.sum() > 1000 and visible.sum() > 0.8 * smooth.sum()  # most points stay visible
        err = np.abs(zb[visible] - zt[visible])
        # Exact on planes; the tail is curved surfaces and corners where four neighbours span two faces.
        assert np.median(err) < 1e-5 and np.percentile(err, 90) < 1e-3
        ui, vi = np.round(pb[inside, 0]).astype(int)[visible], np.round(pb[inside, 1]).astype(int)[visible]
        ca = rgb_a.reshape(-1, 3)[inside][visible].astype(float)
        cb = rgb_b[np.minimum(vi, K.height - 1), np.minimum(ui, K.width - 1)].astype(float)
        # Same colour from another viewpoint (nearest pixel, so texture detail adds some difference).
        assert np.median(np.abs(ca - cb)) < 12
        checked += int(visible.sum())
    assert checked > 3000


def test_rendering_and_rooms_are_deterministic_for_a_seed() -> None:
    K = default_intrinsics(TINY)
    a = make_room(5, texel_density=texel_density_for(K))
    b = make_room(5, texel_density=texel_density_for(K))
    c = make_room(6, texel_density=texel_density_for(K))
    assert np.array_equal(a.atlas.image, b.atlas.image)
    pose = make_trajectory(a.path, 10, **TRAIN_PASS)[3]
    ra, da = render_view(a, pose, K)
    rb, db = render_view(b, pose, K)
    assert np.array_equal(ra, rb) and np.array_equal(da, db)
    assert not np.array_equal(a.objects.box_center, c.objects.box_center)  # another seed, another room
    assert a.atlas.image.shape != c.atlas.image.shape or not np.array_equal(a.atlas.image, c.atlas.image)


def test_textures_are_rich(small_room) -> None:
    """Gradient energy stays well above what smooth noise gives, in every view of a pass, and no surface is flat."""
    scene, K = small_room
    energies = []
    for pose in make_trajectory(scene.path, 8, **TRAIN_PASS):
        rgb, _ = render_view(scene, pose, K)
        g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        energies.append(np.mean(np.abs(np.diff(g, axis=0))) + np.mean(np.abs(np.diff(g, axis=1))))
        corners = cv2.goodFeaturesToTrack(g.astype(np.uint8), 500, 0.01, 3)
        assert corners is not None and len(corners) >= 40
    assert min(energies) > 5.0
    a = scene.atlas
    for s in range(len(scene.surfaces)):
        x, y, w, h = (int(v) for v in (a.x0[s, 0], a.y0[s, 0], a.width[s, 0], a.height[s, 0]))
        assert a.image[y : y + h, x : x + w].std() > 4.0


def test_supersampling_only_changes_boundary_pixels_and_keeps_depth(small_room) -> None:
    scene, K = small_room
    pose = make_trajectory(scene.path, 12, **TRAIN_PASS)[4]
    rgb1, d1 = render_view(scene, pose, K, supersample=1)
    rgb3, d3 = render_view(scene, pose, K, supersample=3)
    assert np.array_equal(d1, d3)
    changed = np.any(rgb1 != rgb3, axis=2)
    assert 0 < changed.mean() < 0.35


# ---------------------------------------------------------------- trajectories


def test_passes_stay_inside_the_room_clear_of_objects_and_upright(small_room) -> None:
    scene, _ = small_room
    ob = scene.objects
    for params in (TRAIN_PASS, TEST_PASS):
        poses = make_trajectory(scene.path, 120, **params)
        for T in poses:
            assert rigidity_problem(T) is None
            assert T[:3, 1] @ np.array([0.0, 0.0, 1.0]) < -0.9  # image y points down: small roll and pitch
        eyes = poses[:, :3, 3]
        assert np.minimum(eyes[:, :2], scene.size[:2] - eyes[:, :2]).min() > 0.8
        assert np.all((eyes[:, 2] > 0.9) & (eyes[:, 2] < scene.size[2] - 0.6))
        assert np.linalg.norm(np.diff(eyes, axis=0), axis=1).max() < 0.15  # smooth
        xy = eyes[:, :2]
        clear = [sdf_box_xy(xy, c[:2], h[:2], y) for c, h, y in zip(ob.box_center, ob.box_half, ob.box_yaw)]
        clear += [np.hypot(*(xy - c).T) - r for c, r in zip(ob.cyl_center, ob.cyl_radius)]
        clear += [np.hypot(*(xy - c[:2]).T) - r for c, r in zip(ob.sph_center, ob.sph_radius)]
        assert len(clear) >= 5 and min(float(c.min()) for c in clear) > CAMERA_CLEARANCE - 1e-6


def test_test_pass_is_separate_but_covers_the_same_room(small_room) -> None:
    scene, K = small_room
    train = make_trajectory(scene.path, 200, **TRAIN_PASS)
    test = make_trajectory(scene.path, 60, **TEST_PASS)
    gap = np.linalg.norm(test[:, None, :3, 3] - train[None, :, :3, 3], axis=2).min(axis=1)
    assert gap.min() > 0.08  # never a training position
    assert gap.max() < 0.5  # but always near one: localizable
    rgb_test, _ = render_view(scene, test[0], K)
    near = np.argsort(np.linalg.norm(train[:, :3, 3] - test[0, :3, 3], axis=1))[:3]
    for i in near:
        assert not np.array_equal(render_view(scene, train[i], K)[0], rgb_test)


# ---------------------------------------------------------------- dataset, layout, CLI


def test_synthesize_writes_an_ace_scene_that_reads_back(tmp_path: Path) -> None:
    out = tmp_path / "scene"
    summary = synthesize(out, seed=1, train_frames=6, test_frames=3, size=TINY)
    assert summary["train_frames"] == 6 and summary["test_frames"] == 3 and summary["size"] == list(TINY)
    train, test = read_split(out, "train"), read_split(out, "test")
    assert len(train) == 6 and len(test) == 3
    K = default_intrinsics(TINY)
    scene = make_room(1, texel_density=texel_density_for(K))
    poses = make_trajectory(scene.path, 6, **TRAIN_PASS)
    for f, T in zip(train.frames, poses):
        np.testing.assert_allclose(f.pose, T, atol=1e-8)
        assert f.intrinsics.fx == pytest.approx(K.fx) and f.intrinsics.cx == pytest.approx(K.cx)
        rgb, depth = render_view(scene, T, K)
        assert np.array_equal(f.load_rgb(), rgb)
        assert np.abs(f.load_depth() - depth).max() <= 0.0005 + 1e-6  # millimetre PNG
    assert json.loads((out / "synth.json").read_text())["seed"] == 1
    assert not list(tmp_path.glob(".scene.*"))  # no leftovers of the atomic move


def test_synthesize_is_deterministic_on_disk(tmp_path: Path) -> None:
    for name in ("a", "b"):
        synthesize(tmp_path / name, seed=3, train_frames=3, test_frames=2, size=TINY)
    for sub in ("train/rgb/frame-00002.png", "test/depth/frame-00001.png", "test/poses/frame-00000.txt"):
        assert (tmp_path / "a" / sub).read_bytes() == (tmp_path / "b" / sub).read_bytes()


def test_built_in_scene_matches_its_stored_reference() -> None:
    """The benchmarks' and tests' numbers hold for this scene only: a dependency that draws it differently (OpenCV 5's
    putText moved the labels' pixels, mean 5/255 per pixel) must fail here, not as a quality floor elsewhere. The
    tolerance (0.5/255 mean) admits last-bit float differences between CPUs."""
    from tests.data.make_synth_reference import FRAMES, render

    ref = np.load(Path(__file__).parent / "data" / "synth_reference.npz")
    got = render()
    for f in FRAMES:
        d = np.abs(got[f].astype(np.float64) - ref[f.replace("/", "__")].astype(np.float64))
        assert d.mean() < 0.5, (
            f"{f}: mean |diff| {d.mean():.2f}/255 against the reference "
            f"(OpenCV {ref['opencv']}, here {cv2.__version__})"
        )


def test_synthesize_rejects_bad_input_and_protects_existing_folders(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="train_frames"):
        synthesize(tmp_path / "x", train_frames=0, size=TINY)
    with pytest.raises(InputError, match="test_frames"):
        synthesize(tmp_path / "x", test_frames=0, size=TINY)
    with pytest.raises(InputError, match="at least"):
        synthesize(tmp_path / "x", size=(4, 64))
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        synthesize(busy, train_frames=2, test_frames=1, size=TINY)
    assert (busy / "keep.txt").read_text() == "mine"
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        synthesize(afile, train_frames=2, test_frames=1, size=TINY)
    synthesize(busy, train_frames=2, test_frames=1, size=TINY, overwrite=True)
    assert not (busy / "keep.txt").exists() and len(read_split(busy, "train")) == 2


def test_render_view_rejects_bad_poses_and_arguments(small_room) -> None:
    scene, K = small_room
    good = make_trajectory(scene.path, 4, **TRAIN_PASS)[0]
    outside = good.copy()
    outside[:3, 3] = [-1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match="outside the room"):
        render_view(scene, outside, K)
    skew = good.copy()
    skew[:3, :3] *= 1.1
    with pytest.raises(ValueError, match="orthonormal"):
        render_view(scene, skew, K)
    with pytest.raises(ValueError, match="4x4"):
        render_view(scene, good[:3], K)
    with pytest.raises(TypeError, match="Intrinsics"):
        render_view(scene, good, K.K)
    with pytest.raises(ValueError, match="supersampling"):
        render_view(scene, good, K, supersample=0)
    with pytest.raises(ValueError, match="room size"):
        make_room(0, size=(1.0, 4.0, 3.0))


def test_random_scene_frames_vary_and_are_consistent() -> None:
    a = random_scene_frames(11, 3, TINY)
    b = random_scene_frames(11, 3, TINY)
    c = random_scene_frames(12, 3, TINY)
    assert len(a) == 3
    rgb, depth, pose, K = a[0]
    assert rgb.shape == TINY + (3,) and rgb.dtype == np.uint8 and depth.shape == TINY and K.shape == (3, 3)
    assert rigidity_problem(pose) is None and np.all(depth > 0)
    assert all(np.array_equal(x.rgb, y.rgb) for x, y in zip(a, b))
    assert not np.allclose(a[0].K, c[0].K) or not np.allclose(a[0].pose, c[0].pose)


def test_cli_synth_writes_json_and_rejects_bad_options(tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(app, ["synth", str(tmp_path / "s"), "--frames", "3", "--test-frames", "2", "--size", "48x64",
                              "--json", str(tmp_path / "s.json")])  # fmt: skip
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "s.json").read_text())
    assert report["train_frames"] == 3 and report["seconds"] > 0
    for args in (["--size", "48by64"], ["--size", "0x64"], ["--frames", "0"], ["--test-frames", "0"]):
        res = runner.invoke(app, ["synth", str(tmp_path / "t"), *args])
        assert res.exit_code == 2, (args, res.output)
        assert "Traceback" not in res.output
    res = runner.invoke(app, ["synth", str(tmp_path / "s"), "--frames", "2", "--size", "48x64"])
    assert res.exit_code == 2 and "not empty" in res.output


def test_screen_rectangle_culling_changes_nothing(small_room) -> None:
    scene, K = small_room
    for pose in make_trajectory(scene.path, 6, **TEST_PASS):
        xs, ys = pixel_rays(K.fx, K.fy, K.cx, K.cy, K.width, K.height)
        d1, c1, _ = cast(scene, pose, xs, ys, K, cull=True)
        d2, c2, _ = cast(scene, pose, xs, ys, K, cull=False)
        assert np.array_equal(d1, d2) and np.array_equal(c1, c2)


def test_mip_filtering_matches_a_box_filtered_high_resolution_render(small_room) -> None:
    """Prefiltered textures: a render looks like a 4x larger render averaged down (no aliasing, no extra blur)."""
    scene, K = small_room
    big = K.resized(4 * K.width, 4 * K.height)
    pose = make_trajectory(scene.path, 12, **TRAIN_PASS)[7]
    small, _ = render_view(scene, pose, K, supersample=1)
    ref = cv2.resize(render_view(scene, pose, big, supersample=1)[0], (K.width, K.height), interpolation=cv2.INTER_AREA)
    diff = np.abs(small.astype(float) - ref.astype(float))
    assert np.median(diff) <= 3 and diff.mean() < 4.0  # measured 3.3; no mipmaps (aliasing) 4.7, one level blurrier 7.6


def test_synth_imports_without_torch_and_degrades_without_photo_packages() -> None:
    """Torch-free, and without scikit-image/matplotlib the room still builds (procedural textures only)."""
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('torch', 'onnx', 'skimage', 'matplotlib'):\n"
        "            raise ImportError('blocked: ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import acesplat.apps.synth_cmd\n"
        "from acesplat.synth import default_intrinsics, make_room, make_trajectory, render_view, TRAIN_PASS\n"
        "scene = make_room(0, texel_density=20.0)\n"
        "pose = make_trajectory(scene.path, 2, **TRAIN_PASS)[0]\n"
        "rgb, depth = render_view(scene, pose, default_intrinsics((24, 32)))\n"
        "print(scene.photo_count, rgb.shape[0], rgb.shape[1], float(rgb.std()))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    photos, h, w, spread = out.stdout.split()
    assert (photos, h, w) == ("0", "24", "32") and float(spread) > 10.0
