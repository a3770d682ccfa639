"""A slow, obviously correct pure-torch Gaussian renderer, for checking the tile rasterizer.

Dense: every pixel evaluates every Gaussian, all sorted by depth, no tiles, no hand-written
gradients (autograd does them). It follows the model documented in acesplat.raster.rasterizer,
written from the equations, not from the kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose
from acesplat.raster import ALPHA_MAX, ALPHA_MIN, DILATION, FRUSTUM_SLACK, MAHA2_MAX, T_MIN


def sh_basis_reference(d: torch.Tensor) -> torch.Tensor:
    """(N, 16) real SH basis at unit directions d (N, 3), 3DGS sign convention."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    pi = math.pi
    c0 = 0.5 / math.sqrt(pi)
    c1 = math.sqrt(3 / (4 * pi))
    c2 = 0.5 * math.sqrt(15 / pi)
    c2b = 0.25 * math.sqrt(5 / pi)
    c2c = 0.25 * math.sqrt(15 / pi)
    c3a = 0.25 * math.sqrt(35 / (2 * pi))
    c3b = 0.5 * math.sqrt(105 / pi)
    c3c = 0.25 * math.sqrt(21 / (2 * pi))
    c3d = 0.25 * math.sqrt(7 / pi)
    c3e = 0.25 * math.sqrt(105 / pi)
    return torch.stack(
        [
            torch.full_like(x, c0),
            -c1 * y,
            c1 * z,
            -c1 * x,
            c2 * x * y,
            -c2 * y * z,
            c2b * (2 * z * z - x * x - y * y),
            -c2 * x * z,
            c2c * (x * x - y * y),
            -c3a * y * (3 * x * x - y * y),
            c3b * x * y * z,
            -c3c * y * (4 * z * z - x * x - y * y),
            c3d * z * (2 * z * z - 3 * x * x - 3 * y * y),
            -c3c * x * (4 * z * z - x * x - y * y),
            c3e * z * (x * x - y * y),
            -c3a * x * (x * x - 3 * y * y),
        ],
        dim=1,
    )


def quat_to_rot(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
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
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


@dataclass
class ReferenceRender:
    color: torch.Tensor  # (H, W, 3)
    alpha: torch.Tensor  # (H, W)
    depth: torch.Tensor  # (H, W)
    means2d: torch.Tensor  # (N, 2), retains its gradient
    stats: dict[str, int]  # how often each special case occurred, so tests can show they are exercised


def render_reference(
    means: torch.Tensor,
    log_scales: torch.Tensor,
    quats: torch.Tensor,
    opacity_logits: torch.Tensor,
    sh: torch.Tensor,
    pose_c2w: np.ndarray,
    k: Intrinsics,
    background: np.ndarray,
    sh_degree: int,
    near: float = 0.01,
    far: float = 1e10,
) -> ReferenceRender:
    dt = means.dtype
    view = torch.as_tensor(invert_pose(pose_c2w), dtype=dt)
    campos = torch.as_tensor(np.asarray(pose_c2w)[:3, 3], dtype=dt)
    rv, tv = view[:3, :3], view[:3, 3]
    p = means @ rv.T + tv
    x, y, z = p.unbind(-1)

    m = quat_to_rot(quats) * torch.exp(log_scales)[:, None, :]
    cov_cam = rv @ (m @ m.transpose(1, 2)) @ rv.T

    w_img, h_img = k.width, k.height
    slack_x = FRUSTUM_SLACK * 0.5 * w_img / k.fx
    slack_y = FRUSTUM_SLACK * 0.5 * h_img / k.fy
    uc = torch.clamp(x / z, -(k.cx / k.fx + slack_x), (w_img - k.cx) / k.fx + slack_x)
    vc = torch.clamp(y / z, -(k.cy / k.fy + slack_y), (h_img - k.cy) / k.fy + slack_y)
    zero = torch.zeros_like(z)
    jac = torch.stack(
        [torch.stack([k.fx / z, zero, -k.fx * uc / z], -1), torch.stack([zero, k.fy / z, -k.fy * vc / z], -1)], dim=1
    )
    cov2 = jac @ cov_cam @ jac.transpose(1, 2) + DILATION * torch.eye(2, dtype=dt)
    a, b, c = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
    det = a * c - b * b
    conic_a, conic_b, conic_c = c / det, -b / det, a / det

    means2d = torch.stack([k.fx * x / z + k.cx, k.fy * y / z + k.cy], dim=-1)
    means2d.retain_grad()
    opac = torch.sigmoid(opacity_logits)

    nk = (sh_degree + 1) ** 2
    dirs = means - campos
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    basis = sh_basis_reference(dirs)[:, :nk]
    rgb = torch.clamp_min(torch.einsum("nk,nkc->nc", basis, sh[:, :nk]) + 0.5, 0.0)

    visible = ((z >= near) & (z <= far) & (det > 0)).detach()

    ys, xs = torch.meshgrid(torch.arange(h_img, dtype=dt), torch.arange(w_img, dtype=dt), indexing="ij")
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # (P, 2), pixel centres at integers
    d = means2d[None, :, :] - pix[:, None, :]  # (P, N, 2)
    dx, dy = d[..., 0], d[..., 1]
    maha2 = conic_a * dx * dx + 2 * conic_b * dx * dy + conic_c * dy * dy
    alpha_raw = opac * torch.exp(-0.5 * maha2)
    valid = (visible[None, :] & (maha2 <= MAHA2_MAX) & (alpha_raw >= ALPHA_MIN)).detach()
    alpha = torch.where(valid, torch.clamp_max(alpha_raw, ALPHA_MAX), torch.zeros_like(alpha_raw))

    order = torch.argsort(torch.where(visible, z, torch.full_like(z, math.inf)).detach(), stable=True)
    alpha = alpha[:, order]
    rgb_s = rgb[order]
    z_s = z[order]
    # Front to back; the first Gaussian that would push transmittance below T_MIN and all behind it
    # are dropped (transmittance only decreases, so "kept" is a prefix).
    keep = (torch.cumprod(1 - alpha, dim=1) >= T_MIN).detach()
    alpha = alpha * keep
    trans_after = torch.cumprod(1 - alpha, dim=1)
    trans_before = torch.cat([torch.ones_like(trans_after[:, :1]), trans_after[:, :-1]], dim=1)
    weights = alpha * trans_before
    t_final = trans_after[:, -1] if alpha.shape[1] else torch.ones(alpha.shape[0], dtype=dt)
    bg = torch.as_tensor(background, dtype=dt)
    color = weights @ rgb_s + t_final[:, None] * bg
    alpha_img = 1 - t_final
    depth_sum = weights @ z_s
    covered = alpha_img > 0
    depth = torch.where(covered, depth_sum / torch.where(covered, alpha_img, torch.ones_like(alpha_img)), 0.0)
    raw_rgb = (torch.einsum("nk,nkc->nc", basis, sh[:, :nk]) + 0.5).detach()
    valid_s = valid[:, order]
    stats = {
        "culled": int((~visible).sum()),
        "terminated_pixels": int((valid_s & ~keep).any(dim=1).sum()),
        "alpha_clamped": int((valid & (alpha_raw > ALPHA_MAX)).sum()),
        "colour_clamped": int((visible[:, None] & (raw_rgb < 0)).sum()),
        "tangent_clamped": int((visible & ((uc != x / z) | (vc != y / z))).sum()),
        "contributions": int((valid_s & keep).sum()),
    }
    return ReferenceRender(
        color=color.reshape(h_img, w_img, 3),
        alpha=alpha_img.reshape(h_img, w_img),
        depth=depth.reshape(h_img, w_img),
        means2d=means2d,
        stats=stats,
    )


def random_scene(
    n: int, seed: int, width: int = 40, height: int = 36, dtype: type = np.float64, sh_degree: int = 3
) -> tuple[dict[str, np.ndarray], np.ndarray, Intrinsics]:
    """Small random scene exercising every branch: Gaussians behind the camera and off-screen,
    crossing tile borders, alpha at the 0.99 clamp, colours at the 0 clamp, stacks opaque enough to
    stop compositing early. Returns (parameter arrays, camera-to-world pose, intrinsics)."""
    from acesplat.core.geometry import make_pose, rodrigues_to_matrix

    rng = np.random.default_rng(seed)
    k = Intrinsics(fx=38.0, fy=41.0, cx=width / 2 - 0.3, cy=height / 2 + 0.4, width=width, height=height)
    pose = make_pose(rodrigues_to_matrix(rng.normal(scale=0.2, size=3)), rng.normal(scale=0.3, size=3))
    z = rng.uniform(0.5, 6.0, n)
    z[: max(1, n // 20)] = rng.uniform(-2.0, 0.005, max(1, n // 20))  # behind / at the near plane
    u = rng.uniform(-0.3 * width, 1.3 * width, n)
    v = rng.uniform(-0.3 * height, 1.3 * height, n)
    sigma_px = rng.uniform(0.7, 6.0, (n, 3))
    if n >= 12:
        # Two wide Gaussians centred far left of the view, where the EWA Jacobian is clamped, that
        # still reach into the image.
        u[-2:] = -0.5 * width
        v[-2:] = height * np.array([0.3, 0.7])
        z[-2:] = np.abs(z[-2:]) + 1.0
        sigma_px[-2:] = 0.3 * width
        # A stack of four near-opaque Gaussians: compositing stops inside it.
        u[-6:-2] = 0.6 * width
        v[-6:-2] = 0.4 * height
        z[-6:-2] = [1.5, 2.0, 2.5, 3.0]
        sigma_px[-6:-2] = 3.0
    cam_pts = np.stack([(u - k.cx) / k.fx * np.abs(z), (v - k.cy) / k.fy * np.abs(z), z], axis=1)
    means = cam_pts @ pose[:3, :3].T + pose[:3, 3]
    log_scales = np.log(sigma_px * np.abs(z)[:, None] / k.fx)
    quats = rng.normal(size=(n, 4))
    logits = rng.normal(scale=2.0, size=n)
    logits[rng.random(n) < 0.15] = 6.0  # alpha clamped at 0.99 near the centre
    if n >= 12:
        logits[-6:-2] = 6.0
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3))
    sh[:, 0] = rng.normal(scale=1.0, size=(n, 3))
    sh[:, 1:] = rng.normal(scale=0.3, size=(n, sh.shape[1] - 1, 3))
    params = {
        "means": means,
        "log_scales": log_scales,
        "quats": quats,
        "opacity_logits": logits,
        "sh": sh,
    }
    return {name: a.astype(dtype) for name, a in params.items()}, pose, k
