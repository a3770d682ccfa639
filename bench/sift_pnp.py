"""The classical reference beside SCR: SIFT + triangulation with the known poses + PnP, on a posed ACE scene.

Mapping: SIFT (4000 features, RootSIFT) on every training image, matched with its nearest training views and
triangulated with their known poses (acesplat.scr.targets.triangulate_targets, the same matching Stage 1 uses for
its targets). Localization: SIFT on the test image, ratio-test matches against every mapped keypoint (FLANN
KD-trees), OpenCV
PnP-RANSAC (USAC_MAGSAC) and LM refinement on the inliers. Prints one JSON line with the accuracy keys of
`acesplat eval` (acesplat.core.metrics.accuracy_summary) and per-frame times.

    python -P bench/sift_pnp.py ../shared/data/herzjesu25 --json runs/sift_herz.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from acesplat.core.geometry import invert_pose, pose_error
from acesplat.core.metrics import FrameResult, accuracy_summary
from acesplat.core.scene import read_split
from acesplat.scr import targets

FEATURES = 4000
RATIO = 0.8
THRESHOLD_PX = 2.0


def gray(frame) -> np.ndarray:
    return cv2.cvtColor(frame.load_rgb(), cv2.COLOR_RGB2GRAY)


def rootsift(sift, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    kp, d = sift.detectAndCompute(g, None)
    pts = np.array([p.pt for p in kp], np.float64).reshape(-1, 2)
    d = d if d is not None else np.zeros((0, 128), np.float32)
    return pts, np.sqrt(d / np.maximum(d.sum(1, keepdims=True), 1e-9)).astype(np.float32)


def build_map(scene: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """Descriptors (M, 128) of the triangulated training keypoints and their world points (M, 3); seconds."""
    t0 = time.perf_counter()
    train = read_split(scene, "train")
    grays = [gray(f) for f in train.frames]
    targets.SIFT_FEATURES = FEATURES
    tg = targets.triangulate_targets(grays, [f.intrinsics for f in train.frames], [f.pose for f in train.frames])
    sift = cv2.SIFT_create(nfeatures=FEATURES)
    descs, points = [], []
    for g, t in zip(grays, tg):
        pts, d = rootsift(sift, g)
        index = {(float(x), float(y)): i for i, (x, y) in enumerate(pts)}
        rows = [index[(float(x), float(y))] for x, y in t.pixels]
        descs.append(d[rows])
        points.append(t.points)
    return np.concatenate(descs), np.concatenate(points), time.perf_counter() - t0


def localize(scene: Path, descs: np.ndarray, points: np.ndarray) -> list[dict]:
    sift = cv2.SIFT_create(nfeatures=FEATURES)
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})  # KD-trees over the map
    matcher.add([descs])
    matcher.train()
    out = []
    for f in read_split(scene, "test").frames:
        g = gray(f)
        t0 = time.perf_counter()
        pts, d = rootsift(sift, g)
        t1 = time.perf_counter()
        knn = matcher.knnMatch(d, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < RATIO * m[1].distance]
        x = pts[[m.queryIdx for m in good]]
        X = points[[m.trainIdx for m in good]]
        t2 = time.perf_counter()
        K = f.intrinsics.K
        params = cv2.UsacParams()
        params.sampler, params.score = cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_MAGSAC
        params.threshold, params.confidence, params.maxIterations = THRESHOLD_PX, 0.9999, 10000
        params.loMethod, params.final_polisher = cv2.LOCAL_OPTIM_SIGMA, cv2.MAGSAC
        ok, _, rvec, tvec, inl = cv2.solvePnPRansac(X, x, K, None, params=params)
        T = None
        if ok and inl is not None and len(inl) >= 6:
            i = inl.ravel()
            rvec, tvec = cv2.solvePnPRefineLM(X[i], x[i], K, None, rvec, tvec)
            w2c = np.eye(4)
            w2c[:3, :3], w2c[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
            T = invert_pose(w2c)
        t3 = time.perf_counter()
        te, re = pose_error(T, f.pose) if T is not None else (float("inf"), float("inf"))
        ms = {"extract": (t1 - t0) * 1e3, "match": (t2 - t1) * 1e3, "pnp": (t3 - t2) * 1e3, "total": (t3 - t0) * 1e3}
        out.append({"name": f.name, "ok": T is not None, "t": te, "r": re, "inliers": 0 if inl is None else len(inl)})
        out[-1].update(ms)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    descs, points, map_s = build_map(a.scene)
    frames = localize(a.scene, descs, points)
    s = accuracy_summary([FrameResult(f["name"], f["ok"], f["t"], f["r"], f["inliers"], f["total"]) for f in frames])
    s["map_seconds"], s["mapped_points"] = map_s, len(points)
    for k in ("extract", "match", "pnp", "total"):
        s[f"{k}_ms_median"] = float(np.median([f[k] for f in frames]))
    s["max_translation_m"] = max(f["t"] for f in frames)
    s["frames_detail"] = frames
    line = json.dumps({k: v for k, v in s.items() if k not in ("frames_detail", "per_frame")})
    print(line)
    if a.json:
        a.json.write_text(json.dumps(s, indent=1))


if __name__ == "__main__":
    main()
