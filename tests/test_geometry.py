"""acesplat.core.geometry against hand-computed rotations, OpenCV, and brute-force references."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from acesplat.core.geometry import (
    OPENGL_TO_OPENCV,
    RIGID_TOL,
    apply_similarity,
    interpolate_pose,
    invert_pose,
    look_at,
    make_pose,
    matrix_to_quat,
    matrix_to_rodrigues,
    pose_error,
    pose_power,
    quat_to_matrix,
    rigidity_problem,
    rodrigues_to_matrix,
    rotation_angle_deg,
    similarity_align,
    transform_points,
)

S = math.sqrt(0.5)

# (quaternion wxyz, rotation matrix) pairs written out by hand.
HAND_CASES = [
    ((1.0, 0.0, 0.0, 0.0), np.eye(3)),
    ((S, 0.0, 0.0, S), np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])),  # +90 deg about z: x -> y
    ((S, S, 0.0, 0.0), np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])),  # +90 deg about x: y -> z
    ((S, 0.0, S, 0.0), np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])),  # +90 deg about y: z -> x
    ((0.0, 1.0, 0.0, 0.0), np.diag([1, -1, -1])),  # 180 deg about x (Shepperd branch k=1)
    ((0.0, 0.0, 1.0, 0.0), np.diag([-1, 1, -1])),  # 180 deg about y (k=2)
    ((0.0, 0.0, 0.0, 1.0), np.diag([-1, -1, 1])),  # 180 deg about z (k=3)
    ((0.5, 0.5, 0.5, 0.5), np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]])),  # 120 deg about (1,1,1): x->y->z->x
]


def random_rotations(n: int, seed: int = 0) -> np.ndarray:
    return quat_to_matrix(np.random.default_rng(seed).normal(size=(n, 4)))


@pytest.mark.parametrize("q, R", HAND_CASES)
def test_quat_to_matrix_hand_cases(q, R) -> None:
    np.testing.assert_allclose(quat_to_matrix(np.array(q)), R, atol=1e-15)


@pytest.mark.parametrize("q, R", HAND_CASES)
def test_matrix_to_quat_hand_cases(q, R) -> None:
    np.testing.assert_allclose(matrix_to_quat(np.asarray(R, dtype=float)), q, atol=1e-15)


def test_quat_90_about_z_rotates_x_to_y() -> None:
    R = quat_to_matrix(np.array([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]))
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)


def test_quat_matrix_round_trips_random() -> None:
    qs = np.random.default_rng(1).normal(size=(200, 4))
    qs /= np.linalg.norm(qs, axis=1, keepdims=True)
    Rs = quat_to_matrix(qs)
    for q, R in zip(qs, Rs):
        q2 = matrix_to_quat(R)
        assert q2[0] >= 0
        np.testing.assert_allclose(q2, q if q[0] >= 0 else -q, atol=1e-12)  # q and -q: the same rotation
        np.testing.assert_allclose(quat_to_matrix(q2), R, atol=1e-12)


def test_quat_to_matrix_normalises_and_batches() -> None:
    q = np.array([[2.0, 0.0, 0.0, 2.0], [0.0, 3.0, 0.0, 0.0]])
    R = quat_to_matrix(q[None])  # (1, 2, 4) -> (1, 2, 3, 3)
    assert R.shape == (1, 2, 3, 3)
    np.testing.assert_allclose(R[0, 0], HAND_CASES[1][1], atol=1e-15)
    np.testing.assert_allclose(R[0, 1], np.diag([1, -1, -1]), atol=1e-15)


def test_quat_matches_opencv_rodrigues() -> None:
    """Axis-angle (OpenCV) and the quaternion (cos t/2, sin t/2 axis) give the same matrix."""
    rng = np.random.default_rng(2)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        t = rng.uniform(0, math.pi)
        q = np.concatenate([[math.cos(t / 2)], math.sin(t / 2) * axis])
        R_cv, _ = cv2.Rodrigues(axis * t)
        np.testing.assert_allclose(quat_to_matrix(q), R_cv, atol=1e-12)
        np.testing.assert_allclose(rodrigues_to_matrix(axis * t), R_cv, atol=1e-12)
    np.testing.assert_array_equal(rodrigues_to_matrix(np.zeros(3)), np.eye(3))


@pytest.mark.parametrize("deg", [0.0, 1e-4, 0.5, 30.0, 90.0, 135.0, 179.9, 180.0])
def test_rotation_angle_known_angles(deg: float) -> None:
    axis = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    R = rodrigues_to_matrix(axis * math.radians(deg))
    assert rotation_angle_deg(R) == pytest.approx(deg, rel=1e-12, abs=1e-12)


def test_rotation_angle_tiny_angles_exact_where_arccos_fails() -> None:
    """At 1e-6 and 1e-8 rad the atan2 form is exact; arccos of the trace is off or collapses to 0."""
    for theta in (1e-6, 1e-8):
        R = rodrigues_to_matrix(np.array([0.0, 0.0, theta]))
        truth = math.degrees(theta)
        assert rotation_angle_deg(R) == pytest.approx(truth, rel=1e-9)
        arccos = math.degrees(math.acos(min(1.0, (np.trace(R) - 1.0) / 2.0)))
        assert abs(arccos - truth) > 1e-5 * truth  # the noise floor this function exists to avoid


def test_rotation_angle_float32_has_no_arccos_noise_floor() -> None:
    """R_est^T R_gt from float32 matrices (as an edge runtime produces): arccos loses ~0.03 deg, atan2 does not."""
    rng = np.random.default_rng(3)
    ours, arccos = [], []
    for Ra in random_rotations(200, seed=4):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        Rb = Ra @ rodrigues_to_matrix(axis * 1e-6)
        R_rel = Ra.astype(np.float32).T @ Rb.astype(np.float32)
        truth = math.degrees(1e-6)
        ours.append(abs(rotation_angle_deg(R_rel) - truth))
        c = np.clip((np.trace(R_rel, dtype=np.float32) - 1) / 2, -1, 1)
        arccos.append(abs(float(np.degrees(np.arccos(c))) - truth))
    assert max(ours) < 1e-4
    assert max(arccos) > 0.01  # measured 0.028 deg with these seeds


def test_pose_error_hand_case() -> None:
    T_gt = make_pose(np.eye(3), [1.0, 2.0, 3.0])
    T_est = make_pose(rodrigues_to_matrix([0.0, math.radians(7.0), 0.0]), [1.0, 2.0, 3.5])
    t_err, r_err = pose_error(T_est, T_gt)
    assert t_err == pytest.approx(0.5)
    assert r_err == pytest.approx(7.0, rel=1e-12)


def test_invert_pose_hand_case() -> None:
    # Camera at C = (1, 2, 3) rotated +90 deg about z: inverse is R^T, -R^T C.
    R = HAND_CASES[1][1].astype(float)
    T = make_pose(R, [1.0, 2.0, 3.0])
    expected = np.array([[0, 1, 0, -2], [-1, 0, 0, 1], [0, 0, 1, -3], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(invert_pose(T), expected, atol=1e-15)


def test_invert_pose_batch_matches_linalg_inv() -> None:
    Rs = random_rotations(10, seed=5)
    ts = np.random.default_rng(6).normal(size=(10, 3)) * 5
    Ts = np.stack([make_pose(R, t) for R, t in zip(Rs, ts)]).reshape(2, 5, 4, 4)
    inv = invert_pose(Ts)
    assert inv.shape == (2, 5, 4, 4)
    np.testing.assert_allclose(inv, np.linalg.inv(Ts), atol=1e-12)
    np.testing.assert_allclose(inv @ Ts, np.broadcast_to(np.eye(4), Ts.shape), atol=1e-12)


def test_transform_points_matches_homogeneous_product() -> None:
    T = make_pose(random_rotations(1, seed=7)[0], [0.5, -1.0, 2.0])
    X = np.random.default_rng(8).normal(size=(7, 3))
    Xh = np.concatenate([X, np.ones((7, 1))], axis=1)
    np.testing.assert_allclose(transform_points(T, X), (Xh @ T.T)[:, :3], atol=1e-12)


def test_look_at_along_x_with_z_up() -> None:
    """OpenCV axes: z toward the target, y down (-up), x right; hand-derived for a camera looking along +x."""
    T = look_at(np.array([1.0, 2.0, 3.0]), np.array([5.0, 2.0, 3.0]), up=np.array([0.0, 0.0, 1.0]))
    expected = np.array([[0, 0, 1, 1], [-1, 0, 0, 2], [0, -1, 0, 3], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(T, expected, atol=1e-15)


def test_look_at_general_axes_properties() -> None:
    rng = np.random.default_rng(9)
    up = np.array([0.0, 0.0, 1.0])
    for _ in range(20):
        eye, target = rng.normal(size=3) * 3, rng.normal(size=3) * 3
        T = look_at(eye, target, up)
        assert rigidity_problem(T) is None
        R = T[:3, :3]
        np.testing.assert_allclose(R[:, 2], (target - eye) / np.linalg.norm(target - eye), atol=1e-12)
        assert R[:, 1] @ up < 0  # image y (down) points against world up
        assert abs(R[:, 0] @ up) < 1e-12  # no roll: the x axis stays horizontal
        # The target lands on the optical axis; a point above it lands above it in the image (smaller y).
        w2c = invert_pose(T)
        p_target = transform_points(w2c, target[None])[0]
        p_above = transform_points(w2c, (target + 0.1 * up)[None])[0]
        np.testing.assert_allclose(p_target[:2], 0.0, atol=1e-9)
        assert p_target[2] > 0 and p_above[1] / p_above[2] < 0


def test_look_at_straight_down_still_rigid() -> None:
    T = look_at(np.array([0.0, 0.0, 5.0]), np.array([0.0, 0.0, 0.0]))
    assert rigidity_problem(T) is None
    np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)


def test_opengl_to_opencv_flip() -> None:
    """A point in front of an OpenGL camera (z < 0, y up) is in front of the flipped OpenCV camera (z > 0, y down)."""
    T_gl = make_pose(random_rotations(1, seed=10)[0], [1.0, 2.0, 3.0])
    T_cv = T_gl @ OPENGL_TO_OPENCV
    np.testing.assert_allclose(T_cv @ OPENGL_TO_OPENCV, T_gl, atol=1e-15)
    X_gl = np.array([[0.2, 0.3, -4.0]])  # ahead of the GL camera, above its axis
    X_world = transform_points(T_gl, X_gl)
    X_cv = transform_points(invert_pose(T_cv), X_world)
    np.testing.assert_allclose(X_cv, [[0.2, -0.3, 4.0]], atol=1e-12)
    assert rigidity_problem(T_cv) is None


def test_rigidity_problem_cases() -> None:
    R = random_rotations(1, seed=11)[0]
    good = make_pose(R, [1.0, 2.0, 3.0])
    assert rigidity_problem(good) is None
    cases = {
        "shape": np.eye(3),
        "non-finite": np.where(np.eye(4) == 1, np.nan, 0.0),
        "last row": np.vstack([good[:3], [0.0, 0.0, 0.1, 1.0]]),
        "orthonormal": make_pose(R * 1.01, [0, 0, 0]),
        "determinant": make_pose(R @ np.diag([1.0, 1.0, -1.0]), [0, 0, 0]),
    }
    expected_words = {
        "shape": "4x4",
        "non-finite": "non-finite",
        "last row": "last row",
        "orthonormal": "orthonormal",
        "determinant": "determinant",
    }
    for key, T in cases.items():
        problem = rigidity_problem(T)
        assert problem is not None and expected_words[key] in problem, (key, problem)
    # Tolerance edge: a stretch of (1 + e) gives |R^T R - I| = 2e + e^2.
    assert rigidity_problem(make_pose(np.diag([1 + 0.49 * RIGID_TOL, 1, 1]), [0, 0, 0])) is None
    assert rigidity_problem(make_pose(np.diag([1 + 0.51 * RIGID_TOL, 1, 1]), [0, 0, 0])) is not None


def test_interpolated_pose_runs_the_straight_line_at_constant_angular_speed() -> None:
    rng = np.random.default_rng(5)
    T0 = make_pose(rodrigues_to_matrix(rng.normal(size=3)), rng.normal(size=3))
    T1 = make_pose(rodrigues_to_matrix(rng.normal(size=3)) @ T0[:3, :3], rng.normal(size=3))
    np.testing.assert_allclose(interpolate_pose(T0, T1, 0.0), T0, atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(T0, T1, 1.0), T1, atol=1e-12)
    total = rotation_angle_deg(T0[:3, :3].T @ T1[:3, :3])
    for t in (0.25, 0.5, 0.8):
        T = interpolate_pose(T0, T1, t)
        assert rigidity_problem(T) is None
        np.testing.assert_allclose(T[:3, 3], (1 - t) * T0[:3, 3] + t * T1[:3, 3], atol=1e-12)
        assert rotation_angle_deg(T0[:3, :3].T @ T[:3, :3]) == pytest.approx(t * total, abs=1e-6)
        assert rotation_angle_deg(T[:3, :3].T @ T1[:3, :3]) == pytest.approx((1 - t) * total, abs=1e-6)
    # The short way round, whichever sign the quaternions come with.
    Rz = rodrigues_to_matrix([0.0, 0.0, np.radians(170.0)])
    mid = interpolate_pose(np.eye(4), make_pose(Rz, np.zeros(3)), 0.5)
    assert rotation_angle_deg(mid[:3, :3]) == pytest.approx(85.0, abs=1e-6)


# ----------------------------------------------------------------------------------- similarity alignment
def _cost(s: float, R: np.ndarray, t: np.ndarray, src: np.ndarray, dst: np.ndarray) -> float:
    return float(((dst - (s * src @ R.T + t)) ** 2).sum())


def test_similarity_align_hand_case() -> None:
    """A triangle turned 90 deg about z, doubled and shifted: the exact (s, R, t) comes back."""
    src = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    dst = 2.0 * src @ Rz.T + np.array([1.0, 2.0, 3.0])
    s, R, t = similarity_align(src, dst)
    assert s == pytest.approx(2.0, abs=1e-12)
    np.testing.assert_allclose(R, Rz, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, 2.0, 3.0], atol=1e-12)


def test_similarity_align_recovers_random_similarities() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        src = rng.normal(size=(rng.integers(3, 40), 3))
        R0 = rodrigues_to_matrix(rng.normal(size=3))
        s0, t0 = float(rng.uniform(0.01, 100.0)), rng.normal(size=3) * 10
        s, R, t = similarity_align(src, s0 * src @ R0.T + t0)
        assert s == pytest.approx(s0, rel=1e-9)
        np.testing.assert_allclose(R, R0, atol=1e-9)
        np.testing.assert_allclose(t, t0, atol=1e-8 * max(1.0, s0))
        s1, R1, t1 = similarity_align(src, src @ R0.T + t0, with_scale=False)
        assert s1 == 1.0
        np.testing.assert_allclose(R1, R0, atol=1e-9)
        np.testing.assert_allclose(t1, t0, atol=1e-9)


def test_similarity_align_noisy_is_the_least_squares_optimum() -> None:
    """With noise: the residual equals Umeyama's closed form, and no perturbation of s, R or t lowers it."""
    rng = np.random.default_rng(4)
    src = rng.normal(size=(30, 3))
    dst = 1.7 * src @ rodrigues_to_matrix([0.3, -0.2, 1.1]).T + [0.5, -1.0, 2.0] + rng.normal(scale=0.05, size=(30, 3))
    s, R, t = similarity_align(src, dst)
    best = _cost(s, R, t, src, dst)
    xs, xd = src - src.mean(0), dst - dst.mean(0)
    D = np.linalg.svd(xd.T @ xs / len(src), compute_uv=False)
    closed = len(src) * ((xd**2).sum() / len(src) - D.sum() ** 2 / ((xs**2).sum() / len(src)))
    assert best == pytest.approx(closed, rel=1e-9)
    for k in range(3):
        for eps in (-1e-3, 1e-3):
            dr = np.zeros(3)
            dr[k] = eps
            assert _cost(s, rodrigues_to_matrix(dr) @ R, t, src, dst) > best
            assert _cost(s, R, t + dr, src, dst) > best
        assert _cost(s * (1 + 1e-3 * (k - 1)), R, t, src, dst) >= best


def test_similarity_align_never_returns_a_reflection() -> None:
    rng = np.random.default_rng(5)
    src = rng.normal(size=(10, 3))
    s, R, _ = similarity_align(src, src * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert s > 0


def test_similarity_align_refuses_bad_inputs() -> None:
    pts = np.random.default_rng(6).normal(size=(5, 3))
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    for src, dst, match in (
        (pts[:2], pts[:2], "at least 3"),
        (pts, pts[:4], r"\(N, 3\)"),
        (line, line, "collinear"),
        (pts, np.full((5, 3), np.nan), "finite"),
    ):
        with pytest.raises(ValueError, match=match):
            similarity_align(src, dst)


def test_apply_similarity_maps_poses_back() -> None:
    rng = np.random.default_rng(7)
    poses = np.stack([make_pose(rodrigues_to_matrix(rng.normal(size=3)), rng.normal(size=3)) for _ in range(6)])
    R0 = rodrigues_to_matrix([0.2, 0.4, -0.3])
    moved = apply_similarity(0.25, R0, np.array([1.0, 0.0, -2.0]), poses)
    assert all(rigidity_problem(T) is None for T in moved)
    s, R, t = similarity_align(moved[:, :3, 3], poses[:, :3, 3])
    np.testing.assert_allclose(apply_similarity(s, R, t, moved), poses, atol=1e-9)
    with pytest.raises(ValueError, match="scale"):
        apply_similarity(0.0, R0, np.zeros(3), poses)


def _random_pose(rng: np.random.Generator, max_angle: float = 2.5) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return make_pose(rodrigues_to_matrix(axis * rng.uniform(0.0, max_angle)), rng.normal(0, 1.0, 3))


def test_matrix_to_rodrigues_matches_opencv_and_round_trips() -> None:
    rng = np.random.default_rng(3)
    for angle in (0.0, 1e-9, 0.3, 2.0, np.pi - 1e-3, np.pi):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = rodrigues_to_matrix(axis * angle)
        w = matrix_to_rodrigues(R)
        np.testing.assert_allclose(rodrigues_to_matrix(w), R, atol=1e-9)
        if 0.0 < angle < np.pi - 1e-2:
            np.testing.assert_allclose(w, cv2.Rodrigues(R)[0].ravel(), atol=1e-9)


def test_pose_power_is_repeated_composition() -> None:
    """Integer powers equal the motion composed with itself, halves compose back to the motion, 0 and 1 are the
    identity and the motion, -1 the inverse: against brute-force products."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        T = _random_pose(rng)
        np.testing.assert_allclose(pose_power(T, 1.0), T, atol=1e-9)
        np.testing.assert_allclose(pose_power(T, 0.0), np.eye(4), atol=1e-12)
        np.testing.assert_allclose(pose_power(T, 2.0), T @ T, atol=1e-8)
        np.testing.assert_allclose(pose_power(T, 3.0), T @ T @ T, atol=1e-8)
        np.testing.assert_allclose(pose_power(T, -1.0), invert_pose(T), atol=1e-8)
        h = pose_power(T, 0.5)
        np.testing.assert_allclose(h @ h, T, atol=1e-8)
    small = make_pose(rodrigues_to_matrix(np.array([1e-10, 0.0, 0.0])), np.array([0.1, 0.0, 0.0]))
    np.testing.assert_allclose(pose_power(small, 3.0)[:3, 3], [0.3, 0.0, 0.0], atol=1e-9)
    with pytest.raises(ValueError, match="4, 4"):
        pose_power(np.eye(3), 2.0)
