"""Numba kernels, one Gaussian per iteration: projection to screen space (EWA) and its backward.

Arrays come in the Gaussians' dtype (float32 or float64); scalars are computed in float64, so the
float32 path only rounds when storing. The backward recomputes the projection with the same helpers
(cheaper than storing it) and visits only Gaussians that own gradient slots, so it never re-decides
culling. Helpers are inlined: numba calls a separate function out of line, with an atomic
reference-count update per array argument, which measured slower than the arithmetic itself.
"""

from __future__ import annotations

import math

from numba import njit

from acesplat.raster._layout import (
    BLUE,
    CA,
    CB,
    CC,
    DEPTH,
    EXT_X,
    EXT_Y,
    G_BLUE,
    G_CA,
    G_CB,
    G_CC,
    G_DEPTH,
    G_GREEN,
    G_MX,
    G_MY,
    G_OPAC,
    G_RED,
    GREEN,
    MAHA2,
    MX,
    MY,
    OPAC,
    POWER_MIN,
    RED,
)

DILATION = 0.3
"""Added to the 2D covariance diagonal (pixels^2): the 3DGS low-pass filter, at least ~1 px footprint."""

FRUSTUM_SLACK = 0.3
"""The Jacobian is evaluated at x/z, y/z clamped this fraction of the half-FOV tangent past the image
edge, as 3DGS does, so Gaussians far outside the view do not get huge affine approximations."""

MAHA2_MAX = 9.0
"""Squared Mahalanobis cut: a Gaussian is truncated at 3 sigma."""

ALPHA_MIN = 1.0 / 255.0
"""Contributions with alpha below this are skipped (3DGS)."""

MAX_EXTENT = 1e7
"""Gaussians whose cut-off ellipse reaches further than this many pixels are culled as degenerate
(keeps every pixel index the kernels compute far inside integer and float32 range)."""

# Real spherical-harmonics constants with the sign convention 3DGS uses (so PLYs render alike).
SH_C0 = 0.5 / math.sqrt(math.pi)
SH_C1 = math.sqrt(3.0 / (4.0 * math.pi))
SH_C2_0 = 0.5 * math.sqrt(15.0 / math.pi)
SH_C2_1 = -0.5 * math.sqrt(15.0 / math.pi)
SH_C2_2 = 0.25 * math.sqrt(5.0 / math.pi)
SH_C2_3 = -0.5 * math.sqrt(15.0 / math.pi)
SH_C2_4 = 0.25 * math.sqrt(15.0 / math.pi)
SH_C3_0 = -0.25 * math.sqrt(35.0 / (2.0 * math.pi))
SH_C3_1 = 0.5 * math.sqrt(105.0 / math.pi)
SH_C3_2 = -0.25 * math.sqrt(21.0 / (2.0 * math.pi))
SH_C3_3 = 0.25 * math.sqrt(7.0 / math.pi)
SH_C3_4 = -0.25 * math.sqrt(21.0 / (2.0 * math.pi))
SH_C3_5 = 0.25 * math.sqrt(105.0 / math.pi)
SH_C3_6 = -0.25 * math.sqrt(35.0 / (2.0 * math.pi))


@njit(cache=True, inline="always")
def sh_basis(x, y, z):
    """The 16 real SH basis values at unit direction (x, y, z), degree 0..3."""
    xx, yy, zz = x * x, y * y, z * z
    return (
        SH_C0,
        -SH_C1 * y,
        SH_C1 * z,
        -SH_C1 * x,
        SH_C2_0 * x * y,
        SH_C2_1 * y * z,
        SH_C2_2 * (2.0 * zz - xx - yy),
        SH_C2_3 * x * z,
        SH_C2_4 * (xx - yy),
        SH_C3_0 * y * (3.0 * xx - yy),
        SH_C3_1 * x * y * z,
        SH_C3_2 * y * (4.0 * zz - xx - yy),
        SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        SH_C3_4 * x * (4.0 * zz - xx - yy),
        SH_C3_5 * z * (xx - yy),
        SH_C3_6 * x * (xx - 3.0 * yy),
    )


@njit(cache=True, inline="always")
def _view_dir(means, i, campos):
    """Unit direction from the camera centre to Gaussian i, and the distance."""
    vx = means[i, 0] - campos[0]
    vy = means[i, 1] - campos[1]
    vz = means[i, 2] - campos[2]
    n = math.sqrt(vx * vx + vy * vy + vz * vz)
    inv = 1.0 / n if n > 0.0 else 0.0
    return vx * inv, vy * inv, vz * inv, n


@njit(cache=True, inline="always")
def _sh_raw_color(sh, i, degree, x, y, z):
    """Colour before the +0.5 offset and clamp: sum_k basis_k * sh[i, k, :].

    Written out term by term: literal tuple indices stay in registers, and small helpers called
    with literal arguments would each compile once per literal.
    """
    bs = sh_basis(x, y, z)
    r = bs[0] * sh[i, 0, 0]
    g = bs[0] * sh[i, 0, 1]
    b = bs[0] * sh[i, 0, 2]
    if degree >= 1:
        r += bs[1] * sh[i, 1, 0] + bs[2] * sh[i, 2, 0] + bs[3] * sh[i, 3, 0]
        g += bs[1] * sh[i, 1, 1] + bs[2] * sh[i, 2, 1] + bs[3] * sh[i, 3, 1]
        b += bs[1] * sh[i, 1, 2] + bs[2] * sh[i, 2, 2] + bs[3] * sh[i, 3, 2]
    if degree >= 2:
        r += bs[4] * sh[i, 4, 0] + bs[5] * sh[i, 5, 0] + bs[6] * sh[i, 6, 0] + bs[7] * sh[i, 7, 0] + bs[8] * sh[i, 8, 0]
        g += bs[4] * sh[i, 4, 1] + bs[5] * sh[i, 5, 1] + bs[6] * sh[i, 6, 1] + bs[7] * sh[i, 7, 1] + bs[8] * sh[i, 8, 1]
        b += bs[4] * sh[i, 4, 2] + bs[5] * sh[i, 5, 2] + bs[6] * sh[i, 6, 2] + bs[7] * sh[i, 7, 2] + bs[8] * sh[i, 8, 2]
    if degree >= 3:
        r += (
            bs[9] * sh[i, 9, 0]
            + bs[10] * sh[i, 10, 0]
            + bs[11] * sh[i, 11, 0]
            + bs[12] * sh[i, 12, 0]
            + bs[13] * sh[i, 13, 0]
            + bs[14] * sh[i, 14, 0]
            + bs[15] * sh[i, 15, 0]
        )
        g += (
            bs[9] * sh[i, 9, 1]
            + bs[10] * sh[i, 10, 1]
            + bs[11] * sh[i, 11, 1]
            + bs[12] * sh[i, 12, 1]
            + bs[13] * sh[i, 13, 1]
            + bs[14] * sh[i, 14, 1]
            + bs[15] * sh[i, 15, 1]
        )
        b += (
            bs[9] * sh[i, 9, 2]
            + bs[10] * sh[i, 10, 2]
            + bs[11] * sh[i, 11, 2]
            + bs[12] * sh[i, 12, 2]
            + bs[13] * sh[i, 13, 2]
            + bs[14] * sh[i, 14, 2]
            + bs[15] * sh[i, 15, 2]
        )
    return r, g, b


@njit(cache=True, inline="always")
def _sh_backward(sh, i, degree, x, y, z, vr, vg, vb, v_sh):
    """Write dL/dsh[i] for colour gradient (vr, vg, vb); return dL/d(unit direction)."""
    bs = sh_basis(x, y, z)
    v_sh[i, 0, 0] = bs[0] * vr
    v_sh[i, 0, 1] = bs[0] * vg
    v_sh[i, 0, 2] = bs[0] * vb
    ux = 0.0
    uy = 0.0
    uz = 0.0
    if degree >= 1:
        v_sh[i, 1, 0] = bs[1] * vr
        v_sh[i, 1, 1] = bs[1] * vg
        v_sh[i, 1, 2] = bs[1] * vb
        v_sh[i, 2, 0] = bs[2] * vr
        v_sh[i, 2, 1] = bs[2] * vg
        v_sh[i, 2, 2] = bs[2] * vb
        v_sh[i, 3, 0] = bs[3] * vr
        v_sh[i, 3, 1] = bs[3] * vg
        v_sh[i, 3, 2] = bs[3] * vb
        w1 = sh[i, 1, 0] * vr + sh[i, 1, 1] * vg + sh[i, 1, 2] * vb
        w2 = sh[i, 2, 0] * vr + sh[i, 2, 1] * vg + sh[i, 2, 2] * vb
        w3 = sh[i, 3, 0] * vr + sh[i, 3, 1] * vg + sh[i, 3, 2] * vb
        ux -= SH_C1 * w3
        uy -= SH_C1 * w1
        uz += SH_C1 * w2
    if degree >= 2:
        v_sh[i, 4, 0] = bs[4] * vr
        v_sh[i, 4, 1] = bs[4] * vg
        v_sh[i, 4, 2] = bs[4] * vb
        v_sh[i, 5, 0] = bs[5] * vr
        v_sh[i, 5, 1] = bs[5] * vg
        v_sh[i, 5, 2] = bs[5] * vb
        v_sh[i, 6, 0] = bs[6] * vr
        v_sh[i, 6, 1] = bs[6] * vg
        v_sh[i, 6, 2] = bs[6] * vb
        v_sh[i, 7, 0] = bs[7] * vr
        v_sh[i, 7, 1] = bs[7] * vg
        v_sh[i, 7, 2] = bs[7] * vb
        v_sh[i, 8, 0] = bs[8] * vr
        v_sh[i, 8, 1] = bs[8] * vg
        v_sh[i, 8, 2] = bs[8] * vb
        w4 = sh[i, 4, 0] * vr + sh[i, 4, 1] * vg + sh[i, 4, 2] * vb
        w5 = sh[i, 5, 0] * vr + sh[i, 5, 1] * vg + sh[i, 5, 2] * vb
        w6 = sh[i, 6, 0] * vr + sh[i, 6, 1] * vg + sh[i, 6, 2] * vb
        w7 = sh[i, 7, 0] * vr + sh[i, 7, 1] * vg + sh[i, 7, 2] * vb
        w8 = sh[i, 8, 0] * vr + sh[i, 8, 1] * vg + sh[i, 8, 2] * vb
        ux += SH_C2_0 * y * w4 - 2.0 * SH_C2_2 * x * w6 + SH_C2_3 * z * w7 + 2.0 * SH_C2_4 * x * w8
        uy += SH_C2_0 * x * w4 + SH_C2_1 * z * w5 - 2.0 * SH_C2_2 * y * w6 - 2.0 * SH_C2_4 * y * w8
        uz += SH_C2_1 * y * w5 + 4.0 * SH_C2_2 * z * w6 + SH_C2_3 * x * w7
    if degree >= 3:
        v_sh[i, 9, 0] = bs[9] * vr
        v_sh[i, 9, 1] = bs[9] * vg
        v_sh[i, 9, 2] = bs[9] * vb
        v_sh[i, 10, 0] = bs[10] * vr
        v_sh[i, 10, 1] = bs[10] * vg
        v_sh[i, 10, 2] = bs[10] * vb
        v_sh[i, 11, 0] = bs[11] * vr
        v_sh[i, 11, 1] = bs[11] * vg
        v_sh[i, 11, 2] = bs[11] * vb
        v_sh[i, 12, 0] = bs[12] * vr
        v_sh[i, 12, 1] = bs[12] * vg
        v_sh[i, 12, 2] = bs[12] * vb
        v_sh[i, 13, 0] = bs[13] * vr
        v_sh[i, 13, 1] = bs[13] * vg
        v_sh[i, 13, 2] = bs[13] * vb
        v_sh[i, 14, 0] = bs[14] * vr
        v_sh[i, 14, 1] = bs[14] * vg
        v_sh[i, 14, 2] = bs[14] * vb
        v_sh[i, 15, 0] = bs[15] * vr
        v_sh[i, 15, 1] = bs[15] * vg
        v_sh[i, 15, 2] = bs[15] * vb
        w9 = sh[i, 9, 0] * vr + sh[i, 9, 1] * vg + sh[i, 9, 2] * vb
        w10 = sh[i, 10, 0] * vr + sh[i, 10, 1] * vg + sh[i, 10, 2] * vb
        w11 = sh[i, 11, 0] * vr + sh[i, 11, 1] * vg + sh[i, 11, 2] * vb
        w12 = sh[i, 12, 0] * vr + sh[i, 12, 1] * vg + sh[i, 12, 2] * vb
        w13 = sh[i, 13, 0] * vr + sh[i, 13, 1] * vg + sh[i, 13, 2] * vb
        w14 = sh[i, 14, 0] * vr + sh[i, 14, 1] * vg + sh[i, 14, 2] * vb
        w15 = sh[i, 15, 0] * vr + sh[i, 15, 1] * vg + sh[i, 15, 2] * vb
        xx, yy, zz = x * x, y * y, z * z
        ux += (
            6.0 * SH_C3_0 * x * y * w9
            + SH_C3_1 * y * z * w10
            - 2.0 * SH_C3_2 * x * y * w11
            - 6.0 * SH_C3_3 * x * z * w12
            + SH_C3_4 * (4.0 * zz - 3.0 * xx - yy) * w13
            + 2.0 * SH_C3_5 * x * z * w14
            + SH_C3_6 * (3.0 * xx - 3.0 * yy) * w15
        )
        uy += (
            SH_C3_0 * (3.0 * xx - 3.0 * yy) * w9
            + SH_C3_1 * x * z * w10
            + SH_C3_2 * (4.0 * zz - xx - 3.0 * yy) * w11
            - 6.0 * SH_C3_3 * y * z * w12
            - 2.0 * SH_C3_4 * x * y * w13
            - 2.0 * SH_C3_5 * y * z * w14
            - 6.0 * SH_C3_6 * x * y * w15
        )
        uz += (
            SH_C3_1 * x * y * w10
            + 8.0 * SH_C3_2 * y * z * w11
            + SH_C3_3 * (6.0 * zz - 3.0 * xx - 3.0 * yy) * w12
            + 8.0 * SH_C3_4 * x * z * w13
            + SH_C3_5 * (xx - yy) * w14
        )
    return ux, uy, uz


@njit(cache=True, inline="always")
def _sigmoid(v):
    if v >= 0.0:
        return 1.0 / (1.0 + math.exp(-v))
    e = math.exp(v)
    return e / (1.0 + e)


@njit(cache=True, inline="always")
def _unit_quat_rotation(quats, i):
    """(ok, norm, w, x, y, z, R as 9 row-major values) of quaternion i; ok False for a zero/NaN quaternion."""
    w = quats[i, 0] * 1.0
    x = quats[i, 1] * 1.0
    y = quats[i, 2] * 1.0
    z = quats[i, 3] * 1.0
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not (n > 0.0 and n < math.inf):
        return False, 1.0, 1.0, 0.0, 0.0, 0.0, (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    inv = 1.0 / n
    w *= inv
    x *= inv
    y *= inv
    z *= inv
    R = (
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )
    return True, n, w, x, y, z, R


@njit(cache=True, inline="always")
def _camera_frame(means, log_scales, quats, i, view):
    """Camera-frame mean p, world rotation R (9), scales s, T = Rview @ R @ diag(s) (9) and the
    camera-frame covariance T T^T (6: xx xy xz yy yz zz)."""
    mx = means[i, 0] * 1.0
    my = means[i, 1] * 1.0
    mz = means[i, 2] * 1.0
    px = view[0, 0] * mx + view[0, 1] * my + view[0, 2] * mz + view[0, 3]
    py = view[1, 0] * mx + view[1, 1] * my + view[1, 2] * mz + view[1, 3]
    pz = view[2, 0] * mx + view[2, 1] * my + view[2, 2] * mz + view[2, 3]
    ok, qn, qw, qx, qy, qz, R = _unit_quat_rotation(quats, i)
    s0 = math.exp(log_scales[i, 0] * 1.0)
    s1 = math.exp(log_scales[i, 1] * 1.0)
    s2 = math.exp(log_scales[i, 2] * 1.0)
    # M = R diag(s); T = view_R @ M
    m00, m01, m02 = R[0] * s0, R[1] * s1, R[2] * s2
    m10, m11, m12 = R[3] * s0, R[4] * s1, R[5] * s2
    m20, m21, m22 = R[6] * s0, R[7] * s1, R[8] * s2
    t00 = view[0, 0] * m00 + view[0, 1] * m10 + view[0, 2] * m20
    t01 = view[0, 0] * m01 + view[0, 1] * m11 + view[0, 2] * m21
    t02 = view[0, 0] * m02 + view[0, 1] * m12 + view[0, 2] * m22
    t10 = view[1, 0] * m00 + view[1, 1] * m10 + view[1, 2] * m20
    t11 = view[1, 0] * m01 + view[1, 1] * m11 + view[1, 2] * m21
    t12 = view[1, 0] * m02 + view[1, 1] * m12 + view[1, 2] * m22
    t20 = view[2, 0] * m00 + view[2, 1] * m10 + view[2, 2] * m20
    t21 = view[2, 0] * m01 + view[2, 1] * m11 + view[2, 2] * m21
    t22 = view[2, 0] * m02 + view[2, 1] * m12 + view[2, 2] * m22
    T = (t00, t01, t02, t10, t11, t12, t20, t21, t22)
    cov = (
        t00 * t00 + t01 * t01 + t02 * t02,
        t00 * t10 + t01 * t11 + t02 * t12,
        t00 * t20 + t01 * t21 + t02 * t22,
        t10 * t10 + t11 * t11 + t12 * t12,
        t10 * t20 + t11 * t21 + t12 * t22,
        t20 * t20 + t21 * t21 + t22 * t22,
    )
    return px, py, pz, ok, qn, (qw, qx, qy, qz), R, (s0, s1, s2), T, cov


@njit(cache=True, inline="always")
def _jacobian(px, py, pz, fx, fy, lim_xn, lim_xp, lim_yn, lim_yp):
    """EWA affine approximation of the projection at p: J = [[j00, 0, j02], [0, j11, j12]].

    Also returns the clamped tangents and whether each was clamped (then x or y gets no gradient via J).
    """
    iz = 1.0 / pz
    u = px * iz
    v = py * iz
    uc = min(max(u, -lim_xn), lim_xp)
    vc = min(max(v, -lim_yn), lim_yp)
    x_clamped = u < -lim_xn or u > lim_xp
    y_clamped = v < -lim_yn or v > lim_yp
    return fx * iz, -fx * uc * iz, fy * iz, -fy * vc * iz, uc, vc, x_clamped, y_clamped


@njit(cache=True, inline="always")
def _cov2d(j00, j02, j11, j12, cov):
    """J cov J^T as (a, b, c) = (xx, xy, yy), before dilation."""
    sxx, sxy, sxz, syy, syz, szz = cov
    a = j00 * j00 * sxx + 2.0 * j00 * j02 * sxz + j02 * j02 * szz
    b = j00 * j11 * sxy + j00 * j12 * sxz + j02 * j11 * syz + j02 * j12 * szz
    c = j11 * j11 * syy + 2.0 * j11 * j12 * syz + j12 * j12 * szz
    return a, b, c


@njit(cache=True)
def _tangent_limits(fx, fy, cx, cy, width, height):
    """x/z and y/z bounds at which the EWA Jacobian is clamped."""
    return (
        cx / fx + FRUSTUM_SLACK * 0.5 * width / fx,
        (width - cx) / fx + FRUSTUM_SLACK * 0.5 * width / fx,
        cy / fy + FRUSTUM_SLACK * 0.5 * height / fy,
        (height - cy) / fy + FRUSTUM_SLACK * 0.5 * height / fy,
    )


@njit(nogil=True, cache=True)
def project_forward(
    lo,
    hi,
    means,
    log_scales,
    quats,
    opacity_logits,
    sh,
    sh_degree,
    view,
    campos,
    fx,
    fy,
    cx,
    cy,
    width,
    height,
    near,
    far,
    rec,
    bbox,
    radii,
    visible,
    means2d,
):
    """For Gaussians lo..hi-1 fill rec (N, REC_WIDTH), bbox (N, 4) pixel range x0 x1 y0 y1,
    radii (N,), visible (N,) and means2d (N, 2) (zeros where culled). Releases the GIL: chunks run
    on a thread pool."""
    lim_xn, lim_xp, lim_yn, lim_yp = _tangent_limits(fx, fy, cx, cy, width, height)
    for i in range(lo, hi):
        visible[i] = False
        radii[i] = 0
        means2d[i, 0] = 0.0
        means2d[i, 1] = 0.0
        px, py, pz, ok, qn, q, R, s, T, cov = _camera_frame(means, log_scales, quats, i, view)
        if not (ok and pz >= near and pz <= far):
            continue
        op = _sigmoid(opacity_logits[i] * 1.0)
        # Largest squared Mahalanobis distance at which alpha = op * exp(-d2 / 2) still reaches ALPHA_MIN.
        maha2 = 2.0 * math.log(op / ALPHA_MIN) if op > ALPHA_MIN else 0.0
        if not (maha2 > 0.0):
            continue
        maha2 = min(maha2, MAHA2_MAX)
        j00, j02, j11, j12, uc, vc, xcl, ycl = _jacobian(px, py, pz, fx, fy, lim_xn, lim_xp, lim_yn, lim_yp)
        a, b, c = _cov2d(j00, j02, j11, j12, cov)
        a += DILATION
        c += DILATION
        det = a * c - b * b
        if not (det > 0.0 and det < math.inf):
            continue
        iz = 1.0 / pz
        mx = fx * px * iz + cx
        my = fy * py * iz + cy
        ex = math.sqrt(maha2 * a)
        ey = math.sqrt(maha2 * c)
        if not (ex <= MAX_EXTENT and ey <= MAX_EXTENT):
            continue
        # Pixel centres sit at integer coordinates; the ellipse's bounding box must hit the image.
        if not (mx + ex >= 0.0 and mx - ex <= width - 1.0 and my + ey >= 0.0 and my - ey <= height - 1.0):
            continue
        x0 = int(max(0.0, math.ceil(mx - ex)))
        x1 = int(min(width - 1.0, math.floor(mx + ex)))
        y0 = int(max(0.0, math.ceil(my - ey)))
        y1 = int(min(height - 1.0, math.floor(my + ey)))
        if x0 > x1 or y0 > y1:
            continue
        if sh_degree > 0:
            dx, dy, dz, _ = _view_dir(means, i, campos)
        else:
            dx, dy, dz = 0.0, 0.0, 1.0
        r, g, bl = _sh_raw_color(sh, i, sh_degree, dx, dy, dz)
        visible[i] = True
        mid = 0.5 * (a + c)
        lam = mid + math.sqrt(max(0.1, mid * mid - det))
        radii[i] = int(math.ceil(3.0 * math.sqrt(lam)))
        means2d[i, 0] = mx
        means2d[i, 1] = my
        bbox[i, 0] = x0
        bbox[i, 1] = x1
        bbox[i, 2] = y0
        bbox[i, 3] = y1
        rec[i, MX] = mx
        rec[i, MY] = my
        inv_det = 1.0 / det
        rec[i, CA] = c * inv_det
        rec[i, CB] = -b * inv_det
        rec[i, CC] = a * inv_det
        rec[i, OPAC] = op
        rec[i, RED] = max(r + 0.5, 0.0)
        rec[i, GREEN] = max(g + 0.5, 0.0)
        rec[i, BLUE] = max(bl + 0.5, 0.0)
        rec[i, DEPTH] = pz
        rec[i, POWER_MIN] = -0.5 * maha2
        rec[i, MAHA2] = maha2
        rec[i, EXT_X] = ex
        rec[i, EXT_Y] = ey


@njit(nogil=True, cache=True)
def project_backward(
    lo,
    hi,
    means,
    log_scales,
    quats,
    opacity_logits,
    sh,
    sh_degree,
    view,
    campos,
    fx,
    fy,
    cx,
    cy,
    width,
    height,
    g_offsets,
    slot_grads,
    v_means,
    v_log_scales,
    v_quats,
    v_opacity_logits,
    v_sh,
    v_means2d,
):
    """Sum each visible Gaussian's per-tile gradients and chain them back to its parameters.

    slot_grads[g_offsets[i]:g_offsets[i + 1]] (GRAD_WIDTH columns) are the gradients the tiles
    Gaussian i touched wrote; none for a culled Gaussian. Gaussians are visited in index order so
    parameter reads and gradient writes stream. Outputs are pre-zeroed; culled Gaussians stay zero.
    Handles Gaussians lo..hi-1 and releases the GIL.
    """
    lim_xn, lim_xp, lim_yn, lim_yp = _tangent_limits(fx, fy, cx, cy, width, height)
    for i in range(lo, hi):
        if g_offsets[i] == g_offsets[i + 1]:
            continue
        v_mx = 0.0
        v_my = 0.0
        v_ca = 0.0
        v_cb = 0.0
        v_cc = 0.0
        v_r = 0.0
        v_g = 0.0
        v_b = 0.0
        v_op = 0.0
        v_z = 0.0
        for row in range(g_offsets[i], g_offsets[i + 1]):
            v_mx += slot_grads[row, G_MX]
            v_my += slot_grads[row, G_MY]
            v_ca += slot_grads[row, G_CA]
            v_cb += slot_grads[row, G_CB]
            v_cc += slot_grads[row, G_CC]
            v_r += slot_grads[row, G_RED]
            v_g += slot_grads[row, G_GREEN]
            v_b += slot_grads[row, G_BLUE]
            v_op += slot_grads[row, G_OPAC]
            v_z += slot_grads[row, G_DEPTH]
        v_means2d[i, 0] = v_mx
        v_means2d[i, 1] = v_my

        px, py, pz, ok, qn, q, R, s, T, cov = _camera_frame(means, log_scales, quats, i, view)
        j00, j02, j11, j12, uc, vc, xcl, ycl = _jacobian(px, py, pz, fx, fy, lim_xn, lim_xp, lim_yn, lim_yp)
        a, b, c = _cov2d(j00, j02, j11, j12, cov)
        a += DILATION
        c += DILATION
        det = a * c - b * b

        # Opacity.
        op = _sigmoid(opacity_logits[i] * 1.0)
        v_opacity_logits[i] = v_op * op * (1.0 - op)

        # Colour: SH evaluated along the view direction, +0.5, clamped at 0.
        v_px = 0.0
        v_py = 0.0
        v_pz = v_z
        if sh_degree > 0:
            dx, dy, dz, dist = _view_dir(means, i, campos)
        else:
            dx, dy, dz, dist = 0.0, 0.0, 1.0, 1.0
        r, g, bl = _sh_raw_color(sh, i, sh_degree, dx, dy, dz)
        if r + 0.5 < 0.0:
            v_r = 0.0
        if g + 0.5 < 0.0:
            v_g = 0.0
        if bl + 0.5 < 0.0:
            v_b = 0.0
        ux, uy, uz = _sh_backward(sh, i, sh_degree, dx, dy, dz, v_r, v_g, v_b, v_sh)
        v_wx = 0.0
        v_wy = 0.0
        v_wz = 0.0
        if sh_degree > 0 and dist > 0.0:
            # d(unit dir)/d(vector) = (I - d d^T) / |vector|
            dot = ux * dx + uy * dy + uz * dz
            inv_dist = 1.0 / dist
            v_wx = (ux - dot * dx) * inv_dist
            v_wy = (uy - dot * dy) * inv_dist
            v_wz = (uz - dot * dz) * inv_dist

        # Conic (inverse of [[a, b], [b, c]]) -> 2D covariance.
        inv_det = 1.0 / det
        ca = c * inv_det
        cb = -b * inv_det
        cc = a * inv_det
        v_det = -(v_ca * ca + v_cb * cb + v_cc * cc) * inv_det
        v_a = v_cc * inv_det + v_det * c
        v_b2 = -v_cb * inv_det - 2.0 * v_det * b
        v_c = v_ca * inv_det + v_det * a

        # 2D covariance = J cov J^T.
        sxx, sxy, sxz, syy, syz, szz = cov
        v_sxx = v_a * j00 * j00
        v_sxz = v_a * 2.0 * j00 * j02 + v_b2 * j00 * j12
        v_szz = v_a * j02 * j02 + v_b2 * j02 * j12 + v_c * j12 * j12
        v_sxy = v_b2 * j00 * j11
        v_syz = v_b2 * j02 * j11 + v_c * 2.0 * j11 * j12
        v_syy = v_c * j11 * j11
        v_j00 = v_a * (2.0 * j00 * sxx + 2.0 * j02 * sxz) + v_b2 * (j11 * sxy + j12 * sxz)
        v_j02 = v_a * (2.0 * j00 * sxz + 2.0 * j02 * szz) + v_b2 * (j11 * syz + j12 * szz)
        v_j11 = v_b2 * (j00 * sxy + j02 * syz) + v_c * (2.0 * j11 * syy + 2.0 * j12 * syz)
        v_j12 = v_b2 * (j00 * sxz + j02 * szz) + v_c * (2.0 * j11 * syz + 2.0 * j12 * szz)

        # Jacobian entries -> camera point (x or y gets nothing through a clamped tangent).
        iz = 1.0 / pz
        iz2 = iz * iz
        v_pz += -v_j00 * fx * iz2 + v_j02 * fx * uc * iz2 - v_j11 * fy * iz2 + v_j12 * fy * vc * iz2
        v_uc = -v_j02 * fx * iz
        v_vc = -v_j12 * fy * iz
        if not xcl:
            v_px += v_uc * iz
            v_pz -= v_uc * px * iz2
        if not ycl:
            v_py += v_vc * iz
            v_pz -= v_vc * py * iz2
        # Projected mean.
        v_px += v_mx * fx * iz
        v_py += v_my * fy * iz
        v_pz -= (v_mx * fx * px + v_my * fy * py) * iz2

        # Camera covariance = T T^T with symmetric gradient G (off-diagonals halved): dL/dT = 2 G T.
        g00 = v_sxx
        g11 = v_syy
        g22 = v_szz
        g01 = 0.5 * v_sxy
        g02 = 0.5 * v_sxz
        g12 = 0.5 * v_syz
        t00, t01, t02, t10, t11, t12, t20, t21, t22 = T
        vt00 = 2.0 * (g00 * t00 + g01 * t10 + g02 * t20)
        vt01 = 2.0 * (g00 * t01 + g01 * t11 + g02 * t21)
        vt02 = 2.0 * (g00 * t02 + g01 * t12 + g02 * t22)
        vt10 = 2.0 * (g01 * t00 + g11 * t10 + g12 * t20)
        vt11 = 2.0 * (g01 * t01 + g11 * t11 + g12 * t21)
        vt12 = 2.0 * (g01 * t02 + g11 * t12 + g12 * t22)
        vt20 = 2.0 * (g02 * t00 + g12 * t10 + g22 * t20)
        vt21 = 2.0 * (g02 * t01 + g12 * t11 + g22 * t21)
        vt22 = 2.0 * (g02 * t02 + g12 * t12 + g22 * t22)
        # T = Vr M  ->  dL/dM = Vr^T dL/dT
        vm00 = view[0, 0] * vt00 + view[1, 0] * vt10 + view[2, 0] * vt20
        vm01 = view[0, 0] * vt01 + view[1, 0] * vt11 + view[2, 0] * vt21
        vm02 = view[0, 0] * vt02 + view[1, 0] * vt12 + view[2, 0] * vt22
        vm10 = view[0, 1] * vt00 + view[1, 1] * vt10 + view[2, 1] * vt20
        vm11 = view[0, 1] * vt01 + view[1, 1] * vt11 + view[2, 1] * vt21
        vm12 = view[0, 1] * vt02 + view[1, 1] * vt12 + view[2, 1] * vt22
        vm20 = view[0, 2] * vt00 + view[1, 2] * vt10 + view[2, 2] * vt20
        vm21 = view[0, 2] * vt01 + view[1, 2] * vt11 + view[2, 2] * vt21
        vm22 = view[0, 2] * vt02 + view[1, 2] * vt12 + view[2, 2] * vt22
        # M = R diag(s)
        s0, s1, s2 = s
        v_log_scales[i, 0] = (vm00 * R[0] + vm10 * R[3] + vm20 * R[6]) * s0
        v_log_scales[i, 1] = (vm01 * R[1] + vm11 * R[4] + vm21 * R[7]) * s1
        v_log_scales[i, 2] = (vm02 * R[2] + vm12 * R[5] + vm22 * R[8]) * s2
        G00, G01, G02 = vm00 * s0, vm01 * s1, vm02 * s2
        G10, G11, G12 = vm10 * s0, vm11 * s1, vm12 * s2
        G20, G21, G22 = vm20 * s0, vm21 * s1, vm22 * s2
        qw, qx, qy, qz = q
        vqw = 2.0 * (-qz * G01 + qy * G02 + qz * G10 - qx * G12 - qy * G20 + qx * G21)
        vqx = 2.0 * (qy * G01 + qz * G02 + qy * G10 - 2.0 * qx * G11 - qw * G12 + qz * G20 + qw * G21 - 2.0 * qx * G22)
        vqy = 2.0 * (-2.0 * qy * G00 + qx * G01 + qw * G02 + qx * G10 + qz * G12 - qw * G20 + qz * G21 - 2.0 * qy * G22)
        vqz = 2.0 * (-2.0 * qz * G00 - qw * G01 + qx * G02 + qw * G10 - 2.0 * qz * G11 + qy * G12 + qx * G20 + qy * G21)
        # Through the normalisation q / |q|.
        dotq = vqw * qw + vqx * qx + vqy * qy + vqz * qz
        inv_qn = 1.0 / qn
        v_quats[i, 0] = (vqw - dotq * qw) * inv_qn
        v_quats[i, 1] = (vqx - dotq * qx) * inv_qn
        v_quats[i, 2] = (vqy - dotq * qy) * inv_qn
        v_quats[i, 3] = (vqz - dotq * qz) * inv_qn

        # Camera point -> world mean (p = Vr m + t), plus the SH view-direction path.
        v_means[i, 0] = view[0, 0] * v_px + view[1, 0] * v_py + view[2, 0] * v_pz + v_wx
        v_means[i, 1] = view[0, 1] * v_px + view[1, 1] * v_py + view[2, 1] * v_pz + v_wy
        v_means[i, 2] = view[0, 2] * v_px + view[1, 2] * v_py + view[2, 2] * v_pz + v_wz
