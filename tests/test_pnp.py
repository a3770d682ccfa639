"""The shared PnP solver against exact synthetic correspondences, and the metrics built on it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose, look_at, make_pose, pose_error, rodrigues_to_matrix, transform_points
from acesplat.core.grid import cell_centers, cell_reprojection_errors
from acesplat.core.metrics import FrameResult, accuracy_summary, timing_stats
from acesplat.core.pnp import PNP_METHODS, PnPConfig, solve_from_grid, solve_pnp

INTR = Intrinsics(200.0, 200.0, 79.5, 59.5, 160, 120)


def _grid_scene(rng: np.random.Generator, outliers: float) -> tuple[np.ndarray, np.ndarray]:
    """A coordinate grid (h, w, 3) seen by a known camera: a bumpy wall 3-5 m away, some cells corrupted."""
    T = look_at(np.array([0.3, -0.2, 1.5]), np.array([0.5, 4.0, 1.2]))
    pix = cell_centers(15, 20)
    depth = 3.0 + rng.uniform(0, 2.0, len(pix))
    X = transform_points(T, INTR.unproject(pix, depth))
    bad = rng.random(len(X)) < outliers
    X[bad] += rng.normal(0, 2.0, (bad.sum(), 3))
    return X.reshape(15, 20, 3), T


def test_cell_centres_follow_stride_8() -> None:
    c = cell_centers(2, 3)
    np.testing.assert_array_equal(c, [[4, 4], [12, 4], [20, 4], [4, 12], [12, 12], [20, 12]])


def test_dense_cell_centres_interleave_the_stride_8_ones() -> None:
    dense = cell_centers(4, 6, stride=4)
    np.testing.assert_array_equal(dense[:3], [[4, 4], [8, 4], [12, 4]])
    np.testing.assert_array_equal(dense.reshape(4, 6, 2)[::2, ::2].reshape(-1, 2), cell_centers(2, 3))
    with pytest.raises(ValueError, match="stride"):
        cell_centers(2, 3, stride=2)


@pytest.mark.parametrize("method", PNP_METHODS)
def test_methods_recover_exact_pose_with_outliers(method: str) -> None:
    coords, T = _grid_scene(np.random.default_rng(1), outliers=0.4)
    res = solve_from_grid(coords, INTR, method=method, min_inliers=50)
    assert res.localized
    t, r = pose_error(res.T_c2w, T)
    assert t < 1e-6 and r < 1e-4
    assert 150 <= res.inliers <= 300


def test_gate_marks_few_inliers_as_not_localized() -> None:
    coords, _ = _grid_scene(np.random.default_rng(2), outliers=0.0)
    res = solve_from_grid(coords, INTR, min_inliers=1000)
    assert not res.localized and res.T_c2w is not None


def test_garbage_is_not_localized() -> None:
    rng = np.random.default_rng(3)
    res = solve_pnp(cell_centers(15, 20), rng.normal(0, 5, (300, 3)), INTR)
    assert not res.localized


def test_non_finite_predictions_are_ignored() -> None:
    coords, T = _grid_scene(np.random.default_rng(4), outliers=0.0)
    coords[0, :5] = np.nan
    res = solve_from_grid(coords, INTR)
    assert res.localized and res.correspondences == 295


def test_accuracy_summary_counts_failures_as_misses() -> None:
    rs = [
        FrameResult("a", True, 0.01, 0.5, 100, 10.0),
        FrameResult("b", True, 0.07, 1.0, 100, 20.0),
        FrameResult("c", True, 0.2, 3.0, 100, 30.0),
        FrameResult("d", False, float("inf"), float("inf"), 3, 40.0),
    ]
    s = accuracy_summary(rs)
    assert s["frames"] == 4 and s["localized"] == 3
    assert s["recall_5cm_5deg"] == 25.0
    assert s["recall_10cm_5deg"] == 50.0
    assert s["recall_25cm_2deg"] == 50.0
    assert s["median_translation_m"] == pytest.approx(0.135)
    assert s["mean_ms"] == pytest.approx(25.0)
    assert s["per_frame"][3]["translation_m"] is None
    assert s["per_frame"][0]["pose_c2w"] is None  # no estimate recorded
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 2.0, 3.0)
    assert FrameResult("e", True, 0.0, 0.0, 9, 1.0, pose).as_dict()["pose_c2w"] == pose.tolist()


def test_timing_stats_against_hand_values() -> None:
    st = timing_stats(list(range(1, 101)))
    assert st["mean"] == pytest.approx(50.5)
    assert st["p50"] == pytest.approx(50.5)
    assert st["p90"] == pytest.approx(90.1)
    assert st["p99"] == pytest.approx(99.01)
    assert st["max"] == 100


@pytest.mark.parametrize("method", ["ransac_ap3p", "usac_magsac"])
def test_same_predictions_give_the_same_pose(method: str) -> None:
    """RANSAC is seeded per call: parity checks and replays compare solutions, not random draws."""
    import cv2

    coords, _ = _grid_scene(np.random.default_rng(7), outliers=0.4)
    coords = coords + np.random.default_rng(8).normal(0, 0.05, coords.shape)
    first = solve_from_grid(coords, INTR, method=method).T_c2w
    cv2.randu(np.zeros((100, 100)), 0, 1)  # advance OpenCV's global generator in between
    again = solve_from_grid(coords, INTR, method=method).T_c2w
    np.testing.assert_array_equal(first, again)


def test_a_mirror_pose_from_the_first_solver_falls_back_to_magsac(monkeypatch) -> None:
    import cv2

    from acesplat.core import pnp

    coords, T = _grid_scene(np.random.default_rng(5), outliers=0.2)
    real = cv2.solvePnPRansac
    calls = []

    def first_returns_the_mirror(*args, **kwargs):
        calls.append("usac" if "params" in kwargs else "p3p")
        if "params" in kwargs:
            return real(*args, **kwargs)
        # The true pose turned half a turn about its own y axis: every scene point lands behind the camera.
        w2c = invert_pose(T)
        flip = np.diag([-1.0, 1.0, -1.0])
        rvec, _ = cv2.Rodrigues(flip @ w2c[:3, :3])
        return True, rvec, (flip @ w2c[:3, 3]).reshape(3, 1), np.arange(300).reshape(-1, 1)

    monkeypatch.setattr(pnp.cv2, "solvePnPRansac", first_returns_the_mirror)
    res = solve_from_grid(coords, INTR, method="ransac_ap3p")  # OpenCV's AP3P is the solver that can mirror
    assert calls == ["p3p", "usac"]
    assert res.localized
    t, r = pose_error(res.T_c2w, T)
    assert t < 1e-6 and r < 1e-4
    calls.clear()
    alone = solve_from_grid(coords, INTR, method="ransac_ap3p", fallback=None)
    assert calls == ["p3p"] and not alone.localized


def _nudged(T: np.ndarray, cm: float, deg: float) -> np.ndarray:
    d = np.eye(4)
    d[:3, :3] = cv2.Rodrigues(np.deg2rad(np.array([deg, 0.0, 0.0])).reshape(3, 1))[0]
    d[:3, 3] = [cm / 100.0, 0.0, 0.0]
    return T @ d


def test_a_good_prior_skips_ransac_and_gives_ransacs_pose(monkeypatch: pytest.MonkeyPatch) -> None:
    coords, T = _grid_scene(np.random.default_rng(5), outliers=0.4)
    ransac = solve_from_grid(coords, INTR, method="batch_p3p")
    import acesplat.core.pnp as pnp

    def no_ransac(*a, **kw):
        raise AssertionError("RANSAC ran although the prior explains the frame")

    monkeypatch.setattr(pnp, "_ransac_and_refine", no_ransac)
    res = solve_from_grid(coords, INTR, method="batch_p3p", prior_c2w=_nudged(T, 2.0, 0.5))
    assert res.localized and res.inliers == ransac.inliers
    t, r = pose_error(res.T_c2w, ransac.T_c2w)
    assert t < 1e-6 and r < 1e-4


def test_a_wrong_prior_falls_back_to_ransac() -> None:
    coords, T = _grid_scene(np.random.default_rng(6), outliers=0.4)
    ransac = solve_from_grid(coords, INTR, method="batch_p3p")
    for wrong in (_nudged(T, 300.0, 30.0), _nudged(T, 0.0, 180.0)):  # far off; facing away (nothing in front)
        res = solve_from_grid(coords, INTR, method="batch_p3p", prior_c2w=wrong)
        assert res.localized
        np.testing.assert_array_equal(res.T_c2w, ransac.T_c2w)


def test_a_malformed_prior_or_ratio_is_refused() -> None:
    coords, _ = _grid_scene(np.random.default_rng(7), outliers=0.0)
    with pytest.raises(ValueError, match="prior_c2w"):
        solve_from_grid(coords, INTR, prior_c2w=np.eye(3))
    with pytest.raises(ValueError, match="prior_c2w"):
        solve_from_grid(coords, INTR, prior_c2w=np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="prior_min_ratio"):
        PnPConfig(prior_min_ratio=1.5)


def test_cell_reprojection_errors_are_the_pixel_offsets_of_moved_cells() -> None:
    """Cells of a wall 2 m ahead, one moved 3 px sideways, one behind the camera, one NaN, at either stride."""
    k = Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)
    pose = make_pose(rodrigues_to_matrix(np.radians([2.0, -3.0, 1.0])), [0.1, 0.2, -0.3])
    for stride in (8, 4):
        h, w = (48 - 4) // stride + 1, (64 - 4) // stride + 1
        uv = cell_centers(h, w, stride)
        coords = transform_points(pose, k.unproject(uv, np.full(len(uv), 2.0))).reshape(h, w, 3)
        coords[1, 2] += pose[:3, 0] * 2.0 * 3.0 / k.fx
        coords[2, 1] = transform_points(pose, np.array([[0.0, 0.0, -1.0]]))[0]
        coords[0, 0] = np.nan
        err = cell_reprojection_errors(coords, pose, k.K, stride).reshape(h, w)
        assert err[1, 2] == pytest.approx(3.0, abs=1e-6) and np.isinf(err[2, 1]) and np.isnan(err[0, 0])
        rest = np.ones((h, w), bool)
        rest[1, 2] = rest[2, 1] = rest[0, 0] = False
        assert np.abs(err[rest]).max() < 1e-6
