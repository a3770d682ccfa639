"""Sparse coordinate targets from the training images themselves: SIFT matches triangulated with the known poses.

Still RGB + poses only. The reprojection loss leaves depth along each ray free except through
agreement between views; a few thousand triangulated points pin it down early, so a CPU budget of
minutes goes into refining instead of searching.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose

SIFT_FEATURES = 2000
NEIGHBOURS = 4
RATIO = 0.8
EPIPOLAR_PX = 2.0
MAX_REPROJ_PX = 2.0
MIN_ANGLE_DEG = 1.0


@dataclass
class ImageTargets:
    """Keypoints (M, 2) of one training image with their triangulated world points (M, 3) and camera depths (M,)."""

    pixels: np.ndarray
    points: np.ndarray
    depths: np.ndarray


def neighbours(c2ws: list[np.ndarray], k: int) -> list[list[int]]:
    """For each camera, the k others that see most alike: close centres and similar viewing directions."""
    C = np.stack([T[:3, 3] for T in c2ws])
    Z = np.stack([T[:3, 2] for T in c2ws])
    dist = np.linalg.norm(C[:, None] - C[None], axis=2)
    scale = np.median(dist[dist > 0]) if np.any(dist > 0) else 1.0
    cosang = np.clip(Z @ Z.T, -1, 1)
    score = dist / scale + 2.0 * (1 - cosang)
    np.fill_diagonal(score, np.inf)
    return [list(np.argsort(row)[: min(k, len(c2ws) - 1)]) for row in score]


def fundamental(K1: np.ndarray, T1: np.ndarray, K2: np.ndarray, T2: np.ndarray) -> np.ndarray:
    """F with x2^T F x1 = 0 for cameras with camera-to-world poses T1, T2."""
    rel = invert_pose(T2) @ T1  # camera 1 -> camera 2
    R, t = rel[:3, :3], rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(K2).T @ tx @ R @ np.linalg.inv(K1)


def triangulate_targets(
    grays: list[np.ndarray],
    intrinsics: list[Intrinsics],
    c2ws: list[np.ndarray],
    k: int = NEIGHBOURS,
    deadline: float | None = None,
) -> list[ImageTargets]:
    """Per image, keypoints whose match with a neighbouring view triangulates consistently.

    Pairs are matched nearest-first for every image in turn; past ``deadline`` (time.monotonic) no new
    pair is started, so the targets cost a bounded share of a mapping budget.
    """
    sift = cv2.SIFT_create(nfeatures=SIFT_FEATURES)
    kps, descs = [], []
    for g in grays:
        kp, d = sift.detectAndCompute(g, None)
        kps.append(np.array([p.pt for p in kp], np.float64).reshape(-1, 2))
        descs.append(d if d is not None else np.zeros((0, 128), np.float32))
    # RootSIFT: Hellinger kernel matches better than Euclidean on SIFT.
    descs = [np.sqrt(d / np.maximum(d.sum(1, keepdims=True), 1e-9)).astype(np.float32) for d in descs]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    found: list[dict[int, list[np.ndarray]]] = [dict() for _ in grays]
    done = set()
    nbrs_all = neighbours(c2ws, k)
    pairs = [(i, nbrs_all[i][r]) for r in range(k) for i in range(len(grays)) if r < len(nbrs_all[i])]
    for i, j in pairs:
        if deadline is not None and time.monotonic() > deadline:
            break
        if (min(i, j), max(i, j)) in done or len(descs[i]) < 2 or len(descs[j]) < 2:
            continue
        done.add((min(i, j), max(i, j)))
        knn = matcher.knnMatch(descs[i], descs[j], k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < RATIO * m[1].distance]
        if len(good) < 8:
            continue
        qi = np.array([m.queryIdx for m in good])
        tj = np.array([m.trainIdx for m in good])
        x1, x2 = kps[i][qi], kps[j][tj]
        Ki, Kj = intrinsics[i].K, intrinsics[j].K
        F = fundamental(Ki, c2ws[i], Kj, c2ws[j])
        l2 = np.c_[x1, np.ones(len(x1))] @ F.T
        d_epi = np.abs(np.sum(l2 * np.c_[x2, np.ones(len(x2))], 1)) / np.linalg.norm(l2[:, :2], axis=1)
        keep = d_epi < EPIPOLAR_PX
        if keep.sum() < 4:
            continue
        qi, tj, x1, x2 = qi[keep], tj[keep], x1[keep], x2[keep]
        P1 = Ki @ invert_pose(c2ws[i])[:3]
        P2 = Kj @ invert_pose(c2ws[j])[:3]
        Xh = cv2.triangulatePoints(P1, P2, x1.T, x2.T)
        X = (Xh[:3] / Xh[3]).T
        ok = np.isfinite(X).all(1)
        for P, x in ((P1, x1), (P2, x2)):
            ph = np.c_[X, np.ones(len(X))] @ P.T
            ok &= ph[:, 2] > 0
            ok &= np.linalg.norm(ph[:, :2] / ph[:, 2:3] - x, axis=1) < MAX_REPROJ_PX
        r1 = X - c2ws[i][:3, 3]
        r2 = X - c2ws[j][:3, 3]
        cos = np.sum(r1 * r2, 1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1) + 1e-12)
        ok &= np.degrees(np.arccos(np.clip(cos, -1, 1))) > MIN_ANGLE_DEG
        for a, b, p in zip(qi[ok], tj[ok], X[ok]):
            found[i].setdefault(int(a), []).append(p)
            found[j].setdefault(int(b), []).append(p)
    out = []
    for i, f in enumerate(found):
        idx = np.array(sorted(f), dtype=np.int64)
        pts = np.array([np.median(np.stack(f[a]), axis=0) for a in idx]).reshape(-1, 3)
        w2c = invert_pose(c2ws[i])
        depth = pts @ w2c[2, :3] + w2c[2, 3] if len(pts) else np.zeros(0)
        out.append(ImageTargets(kps[i][idx].reshape(-1, 2), pts, depth))
    return out
