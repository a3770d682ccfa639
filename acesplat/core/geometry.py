"""Rigid-body geometry in the one pose convention of the project.

Poses are 4x4 camera-to-world matrices with OpenCV camera axes (x right, y down, z forward).
Quaternions are (w, x, y, z), unit norm, Hamilton convention.
"""

from __future__ import annotations

import numpy as np

RIGID_TOL = 1e-4
"""Tolerance for R^T R = I and det R = 1 when validating user poses."""

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplying a camera-to-world pose by this flips OpenGL camera axes (y up, z back) to OpenCV."""


def rigidity_problem(T: np.ndarray, tol: float = RIGID_TOL) -> str | None:
    """Why ``T`` (4, 4) is not a finite rigid transform, or None if it is."""
    T = np.asarray(T)
    if T.shape != (4, 4):
        return f"pose must be 4x4, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return "pose has non-finite entries"
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        return f"pose last row must be 0 0 0 1, got {T[3].tolist()}"
    R = T[:3, :3]
    ortho = np.abs(R.T @ R - np.eye(3)).max()
    if ortho > tol:
        return f"pose rotation is not orthonormal (max |R^T R - I| = {ortho:.2e})"
    det = np.linalg.det(R)
    if abs(det - 1.0) > tol:
        return f"pose rotation has determinant {det:.6f}, expected 1"
    return None


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``T`` (..., 4, 4) without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from rotation (3, 3) and translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t).reshape(3)
    return T


def transform_points(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points ``X`` (N, 3)."""
    return X @ T[:3, :3].T + T[:3, 3]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) from quaternions (..., 4) in (w, x, y, z) order; normalises first."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion (4,) in (w, x, y, z) order with w >= 0 from a rotation matrix (3, 3).

    Shepperd's method: pick the largest of the four diagonal combinations for stability.
    """
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    cands = np.array([tr, R[0, 0], R[1, 1], R[2, 2]])
    k = int(np.argmax(cands))
    if k == 0:
        s = np.sqrt(1.0 + tr) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, t: float) -> np.ndarray:
    """Camera-to-world pose (4, 4) a fraction ``t`` of the way from T0 to T1 (4, 4): centres on the straight
    line, orientation by spherical interpolation (constant angular speed)."""
    q0, q1 = matrix_to_quat(T0[:3, :3]), matrix_to_quat(T1[:3, :3])
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    angle = np.arccos(min(dot, 1.0))
    if angle < 1e-9:
        q = q0
    else:
        q = (np.sin((1 - t) * angle) * q0 + np.sin(t * angle) * q1) / np.sin(angle)
    return make_pose(quat_to_matrix(q), (1 - t) * T0[:3, 3] + t * T1[:3, 3])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of rotation ``R`` (3, 3) in degrees, via atan2 (no arccos noise floor near 0)."""
    R = np.asarray(R, dtype=np.float64)
    vee = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = np.linalg.norm(vee) / 2.0
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def pose_error(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """(translation error in scene units, rotation error in degrees) between two camera-to-world poses."""
    t_err = float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))
    r_err = rotation_angle_deg(T_est[:3, :3].T @ T_gt[:3, :3])
    return t_err, r_err


def _skew(w: np.ndarray) -> np.ndarray:
    """The cross-product matrix (3, 3) of ``w`` (3,): _skew(w) @ x = w x x."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rodrigues_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix from an axis-angle vector (3,) (the OpenCV rvec)."""
    rvec = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = np.linalg.norm(rvec)
    if theta < 1e-12:
        return np.eye(3)
    Kx = _skew(rvec / theta)
    return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx


def matrix_to_rodrigues(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (3,) of rotation ``R`` (3, 3), angle in [0, pi] (the inverse of rodrigues_to_matrix)."""
    R = np.asarray(R, dtype=np.float64)
    theta = np.radians(rotation_angle_deg(R))
    vee = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-12:
        return vee / 2.0
    if np.pi - theta > 1e-6:
        return vee * (theta / (2.0 * np.sin(theta)))
    # at pi the antisymmetric part vanishes: the axis is the column of R + I with the largest norm
    B = R + np.eye(3)
    k = B[:, int(np.argmax(np.linalg.norm(B, axis=0)))]
    return k / np.linalg.norm(k) * theta


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian V(w) (3, 3): exp of the twist (w, v) has translation V(w) v."""
    theta = float(np.linalg.norm(w))
    W = _skew(w)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * W
    return np.eye(3) + (1.0 - np.cos(theta)) / theta**2 * W + (theta - np.sin(theta)) / theta**3 * W @ W


def pose_power(T: np.ndarray, r: float) -> np.ndarray:
    """The rigid motion ``T`` (4, 4) applied ``r`` times (any real ``r``): exp(r log T) on SE(3), the screw motion a
    constant velocity gives; pose_power(T, 2) = T @ T, pose_power(T, 0.5) twice = T. Rotations below pi."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"pose must be (4, 4), got {T.shape}")
    w = matrix_to_rodrigues(T[:3, :3])
    v = np.linalg.solve(_left_jacobian(w), T[:3, 3])
    return make_pose(rodrigues_to_matrix(r * w), _left_jacobian(r * w) @ (r * v))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target``; image y points along -up."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))  # right = forward x up, so that y = z x x points along -up
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def similarity_align(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``(s, R, t)`` minimising ``sum_i |dst_i - (s R src_i + t)|^2`` over points ``src``, ``dst``
    (N, 3), N >= 3 and not all on one line (Umeyama 1991, with the reflection correction: ``det R = +1``).

    ``with_scale=False`` fixes ``s = 1`` (a rigid alignment). Returns the scale, R (3, 3) and t (3,).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"src and dst must both be (N, 3), got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"a similarity needs at least 3 point pairs, got {len(src)}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("src and dst must be finite")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float((xs**2).sum()) / len(src)
    U, D, Vt = np.linalg.svd(xd.T @ xs / len(src))
    extent = max(float(np.sqrt(var_s * float((xd**2).sum()) / len(src))), 1e-300)
    if D[1] <= 1e-12 * extent:
        raise ValueError("the points are (nearly) collinear or coincident: the rotation is not determined")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def apply_similarity(s: float, R: np.ndarray, t: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Camera-to-world poses (N, 4, 4) moved by the similarity ``x -> s R x + t``: centres mapped, orientations
    rotated by ``R`` (3, 3); still rigid (the scale changes only the units of the translations)."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (N, 4, 4), got {poses.shape}")
    if not (np.isfinite(s) and s > 0):
        raise ValueError(f"scale must be positive and finite, got {s}")
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ np.asarray(R).T + np.asarray(t).reshape(3)
    return out
