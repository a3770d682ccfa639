"""Refinement primitives: keyframe selection, deadlines, row Adam, seeding geometry, coverage, prune/cap, atomic
saving."""

from __future__ import annotations

import os

import numpy as np
import pytest

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import Gaussians, logit
from acesplat.core.geometry import look_at, make_pose, rodrigues_to_matrix
from acesplat.core.ply import read_ply, write_ply
from acesplat.splatcore.lattice import seed_pixels
from acesplat.splatcore.pixel_coords import pixel_depths
from acesplat.splatcore.prune import cap_keep, transparent
from edge.refine.adam import LearningRates, RowAdam
from edge.refine.coverage import analyse_render, frustum_mask, projected_coverage
from edge.refine.deadline import CostEstimate, Deadline
from edge.refine.guard import harmed_views, held_verdict, loaded_bound, psnr
from edge.refine.keyframes import KeyframePolicy, KeyframeSelector, keyframe_decision
from edge.refine.persist import SplatSaver


class FakeClock:
    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def pose_at(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    return make_pose(rodrigues_to_matrix(np.array([0.0, np.radians(yaw_deg), 0.0])), np.array([x, 0.0, 0.0]))


# ----------------------------------------------------------------------------------- keyframes
def test_keyframe_sequence_by_hand() -> None:
    """A hand-made walk: first frame, small moves skipped, a 12 cm move, a 10 degree turn, a lost frame, few inliers."""
    sel = KeyframeSelector(
        KeyframePolicy(
            min_inliers=100, min_inlier_ratio=0.0, min_translation_m=0.10, min_rotation_deg=8.0, min_coverage=0.8
        )
    )
    seq = [
        (pose_at(0.00), 300, True, None, True),  # first
        (pose_at(0.05), 300, True, None, False),  # 5 cm: redundant
        (pose_at(0.09), 300, True, None, False),  # 9 cm from the keyframe: still redundant
        (pose_at(0.12), 300, True, None, True),  # 12 cm: new viewpoint
        (pose_at(0.12, 5.0), 300, True, None, False),  # 5 degrees
        (pose_at(0.12, 10.0), 300, True, None, True),  # 10 degrees
        (pose_at(0.50), 300, False, None, False),  # lost
        (pose_at(0.50), 60, True, None, False),  # passed the PnP gate but too few inliers for refinement
        (pose_at(0.13, 10.0), 300, True, 0.5, True),  # no motion, but the map covers half the view
        (pose_at(0.13, 10.0), 300, True, 0.95, False),  # no motion, well covered
    ]
    for pose, inl, tracking, cov, expected in seq:
        got = sel.consider(pose, inl, tracking, cov)
        assert got == expected, (pose[:3, 3], inl, tracking, cov)
        if got:
            sel.accept(pose)
    assert sel.counts == {"first": 1, "redundant": 4, "viewpoint": 2, "lost": 1, "inliers": 1, "coverage": 1}


def test_rolled_back_keyframe_does_not_move_the_reference() -> None:
    sel = KeyframeSelector(KeyframePolicy(min_inliers=10))
    assert sel.consider(pose_at(0.0), 50, True)
    sel.accept(pose_at(0.0))
    assert sel.consider(pose_at(0.2), 50, True)  # not accepted (say the guard rolled it back) ...
    assert sel.consider(pose_at(0.21), 50, True)  # ... so the next frame nearby is still new


def test_keyframe_decision_rejects_non_finite_pose() -> None:
    assert keyframe_decision(np.full((4, 4), np.nan), 500, True, None, None) == (False, "lost")
    with pytest.raises(ValueError):
        KeyframePolicy(min_coverage=1.5)


# ----------------------------------------------------------------------------------- deadlines
def test_deadline_and_cost_estimate_with_a_fake_clock() -> None:
    clock = FakeClock(10.0)
    d = Deadline.after(0.5, clock)
    est = CostEstimate(prior_s=0.2, safety=1.2)
    assert est.predict() == 0.2 and d.allows(0.2, 0.3) and not d.allows(0.2, 0.31)
    est.record(0.1)
    assert est.predict() == pytest.approx(0.12)
    est.record(0.3)
    assert est.predict() == pytest.approx(1.2 * 0.2)  # median of the recent measurements
    est.record(0.3)
    est.record(5.0)  # one outlier does not take over the prediction
    assert est.predict() == pytest.approx(1.2 * 0.3)
    clock.t = 10.4
    assert d.remaining() == pytest.approx(0.1) and not d.expired()
    d.preempt()
    assert d.expired() and d.at == pytest.approx(10.4)
    clock.t = 10.0
    d2 = Deadline(10.2, clock)
    d2.preempt()  # preempting never extends a deadline
    assert d2.at == pytest.approx(10.0)


def test_a_granted_piece_is_timed_to_the_next_request() -> None:
    """What a piece costs is all the batch runs before it asks again, not only its main call: work after that call
    (culls, copies) is learned by the piece's estimate; a refused piece records nothing."""
    from edge.refine.refiner import grant

    clock = FakeClock(0.0)
    main, after = CostEstimate(0.01, name="main"), CostEstimate(0.0, name="after")

    def batch():
        if (yield ("must", main, 0.0)):
            clock.t += 0.01  # the main call
            clock.t += 0.04  # what follows it before the next request
        yield ("option", after, 0.0)

    gen = batch()
    kind, est, _ = next(gen)
    assert (kind, est.name, est.predict()) == ("must", "main", 0.01)
    kind, est, _ = grant(gen, True, est, clock)
    assert est is after and main.last_s == pytest.approx(0.05) and main.predict() == pytest.approx(1.2 * 0.05)
    with pytest.raises(StopIteration):
        grant(gen, False, est, clock)
    assert after.count == 0


# ----------------------------------------------------------------------------------- Adam
class _Grads:
    def __init__(self, g: Gaussians, value: float) -> None:
        for p in ("means", "log_scales", "quats", "opacity_logits", "sh"):
            setattr(self, p, np.full_like(getattr(g, p), value))


def test_row_adam_first_step_moves_by_the_learning_rate_and_only_masked_rows() -> None:
    """Adam's bias-corrected first step is -lr * sign(grad) (for |grad| >> eps); unmasked rows do not move."""
    g = Gaussians.zeros(4, 1, np.float64)
    before = g.copy()
    lr = LearningRates(means=0.1, log_scales=0.2, quats=0.3, opacity_logits=0.4, sh_dc=0.5, sh_rest=0.6)
    opt = RowAdam(g, lr)
    rows = np.array([True, False, True, False])
    opt.step(g, _Grads(g, 2.0), rows)
    assert np.allclose(g.means[rows], before.means[rows] - 0.1)
    assert np.allclose(g.opacity_logits[rows], -0.4)
    assert np.allclose(g.sh[rows, 0], -0.5) and np.allclose(g.sh[rows, 1:], -0.6)
    for p in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert np.array_equal(getattr(g, p)[~rows], getattr(before, p)[~rows])
    assert list(opt.t) == [1, 0, 1, 0]
    opt.step(g, _Grads(g, -1.0), ~rows)  # rows 1 and 3 start their own bias correction
    assert np.allclose(g.means[~rows], 0.1)


def test_row_adam_matches_a_hand_computed_second_step() -> None:
    g = Gaussians.zeros(1, 0, np.float64)
    opt = RowAdam(g, LearningRates(means=1.0))
    opt.step(g, _Grads(g, 1.0))
    opt.step(g, _Grads(g, 3.0))
    m = 0.9 * 0.1 + 0.1 * 3.0
    v = 0.999 * 0.001 + 0.001 * 9.0
    expected = -1.0 - (m / (1 - 0.9**2)) / (np.sqrt(v / (1 - 0.999**2)) + 1e-15)
    assert g.means[0, 0] == pytest.approx(expected)


# ----------------------------------------------------------------------------------- seeding and coverage
def test_pixel_depths_of_a_plane_are_exact() -> None:
    """Cells on a fronto-parallel wall at 2 m: every pixel (at a different resolution) unprojects onto the wall."""
    k_in = Intrinsics.from_focal(60.0, 64, 48)
    T = look_at(np.array([0.3, -0.2, 1.0]), np.array([0.3, 5.0, 1.0]))  # looking along +y at the wall y = 1.8
    h, w = 6, 8
    ys, xs = np.mgrid[0:h, 0:w]
    uv = np.stack([xs.ravel() * 8 + 4.0, ys.ravel() * 8 + 4.0], 1)
    X = (T[:3, :3] @ k_in.unproject(uv, np.full(h * w, 2.0)).T).T + T[:3, 3]
    coords = X.reshape(h, w, 3)
    k_out = k_in.resized(32, 24)
    pix = pixel_depths(coords, T, k_in, k_out)
    assert pix.valid.all()
    assert np.allclose(pix.depth, 2.0, atol=1e-5)
    assert np.allclose(pix.centres[..., 1], 1.8, atol=1e-5)
    bad = coords.copy()
    bad[2, 3] = np.nan  # one untrusted cell: its neighbours still interpolate from the others
    pix2 = pixel_depths(bad, T, k_in, k_out)
    assert np.allclose(pix2.depth[pix2.valid], 2.0, atol=1e-5) and pix2.valid.mean() > 0.8


def test_pixel_depths_mark_depth_edges_invalid() -> None:
    k = Intrinsics.from_focal(60.0, 64, 48)
    T = np.eye(4)
    z = np.where(np.arange(8)[None, :] < 4, 1.0, 3.0) * np.ones((6, 1))
    ys, xs = np.mgrid[0:6, 0:8]
    uv = np.stack([xs.ravel() * 8 + 4.0, ys.ravel() * 8 + 4.0], 1)
    coords = k.unproject(uv, z.ravel()).reshape(6, 8, 3)
    pix = pixel_depths(coords, T, k, k)
    assert not pix.valid[:, 28:36].any()  # pixels fed by both sides of the edge
    assert pix.valid[:, :16].all() and pix.valid[:, 48:].all()


def test_seed_pixels_respects_spacing_and_budget() -> None:
    rng = np.random.default_rng(0)
    mask = np.ones((40, 60), bool)
    idx, s = seed_pixels(mask, 2, 10_000, rng)
    assert s == 2 and idx.size == 600
    idx, s = seed_pixels(mask, 2, 100, rng)
    assert idx.size <= 100 and s >= 5
    assert seed_pixels(np.zeros((4, 4), bool), 1, 10, rng)[0].size == 0


def test_analyse_render_marks_uncovered_and_wrong_pixels() -> None:
    target = np.full((4, 4, 3), 0.5, np.float32)
    color = target.copy()
    alpha = np.ones((4, 4), np.float32)
    alpha[0, 0] = 0.1
    color[1, 1] = 0.9
    a = analyse_render(color, alpha, target)
    assert a.need.sum() == 2 and a.need[0, 0] and a.need[1, 1]
    assert a.coverage == pytest.approx(15 / 16)
    assert a.mse == pytest.approx(3 * 0.16 / 48)


def test_frustum_mask_and_projected_coverage() -> None:
    k = Intrinsics.from_focal(50.0, 64, 48)
    T = np.eye(4)
    means = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0], [10.0, 0.0, 1.0], [0.66, 0.0, 1.0]])
    log_scales = np.log(np.array([[0.01] * 3, [0.01] * 3, [0.01] * 3, [0.05] * 3]))
    assert list(frustum_mask(means, log_scales, T, k)) == [True, False, False, True]
    depth = np.full((6, 8), 2.0)
    cov = projected_coverage(means[:1], T, k, depth)
    assert cov == pytest.approx(1 / 48)
    assert projected_coverage(means[:1], T, k, np.full((6, 8), 5.0)) == 0.0  # depth disagrees with the cells


def test_held_verdict() -> None:
    assert held_verdict(1.0, 0.5, [0.1, 0.1], [0.12, 0.1], tolerance=0.3)
    assert not held_verdict(1.0, 0.5, [0.1, 0.1], [0.14, 0.1], tolerance=0.3)  # one held view 40% worse
    assert not held_verdict(0.1, 0.09, [0.1], [0.12], tolerance=0.3)  # the sum rose
    assert held_verdict(1.0, 0.9, [], [])


def test_harmed_views_hold_each_view_to_the_loaded_map_not_the_average() -> None:
    loaded = [0.010, 0.020, 0.040]
    after = [0.005, 0.010, 0.041]  # mean PSNR rises by 2 dB, the third view falls by 0.1 dB
    assert np.mean([psnr(m) for m in after]) > np.mean([psnr(m) for m in loaded]) + 1.0
    assert harmed_views(after, loaded, tolerance_db=0.05) == [2]
    assert harmed_views(after, loaded, tolerance_db=0.2) == []  # 0.1 dB is within a 0.2 dB tolerance
    assert harmed_views(loaded, loaded, tolerance_db=0.0) == []
    # the bound is the loaded error made tolerance_db of PSNR worse
    assert psnr(loaded_bound(0.01, 0.5)) == pytest.approx(psnr(0.01) - 0.5, abs=1e-6)
    with pytest.raises(ValueError, match="after"):
        harmed_views([0.1], [0.1, 0.2], 0.05)
    with pytest.raises(ValueError, match="tolerance"):
        loaded_bound(0.1, -1.0)


def test_harm_report_fails_a_run_when_any_view_falls() -> None:
    from edge.refine.session import harm_report

    r = harm_report(np.array([20.0, 25.0, 30.0]), np.array([23.0, 28.0, 29.9]), 0.05)
    assert r["failed"] and r["views_harmed"] == 1 and r["harmed"][0]["view"] == 2
    assert r["psnr_worst_change_db"] == pytest.approx(-0.1)
    r = harm_report(np.array([20.0, np.inf]), np.array([20.02, np.inf]), 0.05)
    assert not r["failed"] and r["harmed"] == [] and r["psnr_worst_change_db"] == 0.0
    assert not harm_report(np.array([20.0]), np.array([19.97]), 0.05)["failed"]  # within the tolerance
    with pytest.raises(ValueError, match="matching"):
        harm_report(np.zeros(2), np.zeros(3), 0.05)


# ----------------------------------------------------------------------------------- prune and cap
def test_prune_and_cap() -> None:
    g = Gaussians.zeros(6, 0)
    g.opacity_logits[:] = logit(np.array([0.9, 0.001, 0.5, 0.7, 0.002, 0.5]))
    g.means[3, 0] = np.nan
    assert list(transparent(g)) == [False, True, False, True, True, False]
    keep = cap_keep(g, 3)
    assert keep.sum() == 3 and keep[0] and keep[3] and keep[2]  # ties (0.5, 0.5) keep the earlier one
    assert cap_keep(g, 10).all()


# ----------------------------------------------------------------------------------- atomic saving
def test_saver_keeps_the_previous_file_when_the_disk_fills(tmp_path, monkeypatch) -> None:
    path = tmp_path / "refined.ply"
    clock = FakeClock(0.0)
    saver = SplatSaver(path, every_s=10.0, clock=clock)
    g1 = Gaussians.zeros(5, 0)
    g1.means[:, 0] = np.arange(5)
    saver.mark_dirty()
    assert saver.maybe_save(g1) and saver.saves == 1
    good = path.read_bytes()
    saver.mark_dirty()
    clock.t = 5.0
    assert not saver.maybe_save(g1)  # not due yet
    clock.t = 11.0
    real_fsync = os.fsync

    def full_disk(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    g2 = Gaussians.zeros(50, 0)
    assert saver.maybe_save(g2) is False
    assert saver.failures == 1 and "No space left" in saver.last_error
    assert path.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["refined.ply"]  # the temporary file is gone
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert saver.save(g2) and len(read_ply(path)) == 50


def test_saver_survives_a_crash_mid_write(tmp_path, monkeypatch) -> None:
    """An exception between writing and renaming (a crash) never replaces the good file with a partial one."""
    path = tmp_path / "map.ply"
    write_ply(path, Gaussians.zeros(3, 0))
    good = path.read_bytes()
    import acesplat.core.atomic as atomic

    def crash(src, dst):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(atomic.os, "replace", crash)
    saver = SplatSaver(path, every_s=30.0)
    assert not saver.save(Gaussians.zeros(30, 0))
    assert path.read_bytes() == good and len(list(tmp_path.iterdir())) == 1
