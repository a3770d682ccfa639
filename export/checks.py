"""Self-checks every export runs: the FP32 graph against torch, the INT8 graph by localization accuracy.

The numbers are written into the manifest so a bundle carries the evidence of its own fidelity.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from acesplat.core.bundle import SCR_COORDS_OUTPUT, SCR_FEATURES_OUTPUT
from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import pose_error
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.core.metrics import FrameResult, accuracy_summary
from acesplat.core.pnp import solve_from_grid
from acesplat.core.preprocess import to_gray_input
from acesplat.core.scene import Frame
from acesplat.scr.network import SCRNetwork, normalize_gray

ProgressFn = Callable[[str, float, dict], None]


@dataclass
class CheckFrame:
    """A frame prepared at the bundle's input size: grayscale (H, W) uint8, intrinsics, true pose."""

    name: str
    gray: np.ndarray
    intrinsics: Intrinsics
    pose: np.ndarray


def prepare_frames(frames: Sequence[Frame], size_hw: tuple[int, int]) -> list[CheckFrame]:
    out = []
    for f in frames:
        gray, intr = to_gray_input(f.load_rgb(), f.intrinsics, size_hw)
        out.append(CheckFrame(f.name, gray, intr, f.pose))
    return out


def onnx_session(path: str | Path) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.log_severity_level = 3
    return ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])


def onnx_outputs(
    sess: ort.InferenceSession, gray: np.ndarray, features: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    """(h, w, 3) coordinates and, if asked and the graph has them, the (C, h, w) features for a grayscale (H, W)
    image."""
    name = sess.get_inputs()[0].name
    outs = [o.name for o in sess.get_outputs()]
    want = [SCR_COORDS_OUTPUT if SCR_COORDS_OUTPUT in outs else outs[0]]
    if features and SCR_FEATURES_OUTPUT in outs:
        want.append(SCR_FEATURES_OUTPUT)
    got = sess.run(want, {name: gray.astype(np.float32)[None, None]})
    return np.moveaxis(got[0][0], 0, -1), (got[1][0] if len(got) > 1 else None)


def onnx_coords(sess: ort.InferenceSession, gray: np.ndarray) -> np.ndarray:
    """(h, w, 3) coordinates from an ONNX session for a grayscale (H, W) image."""
    return onnx_outputs(sess, gray)[0]


@torch.no_grad()
def torch_coords(net: SCRNetwork, gray: np.ndarray, stride: int = OUTPUT_STRIDE) -> np.ndarray:
    return net(torch.from_numpy(gray).float()[None, None], stride)[0].permute(1, 2, 0).numpy()


@torch.no_grad()
def torch_features(net: SCRNetwork, gray: np.ndarray, stride: int = OUTPUT_STRIDE) -> np.ndarray:
    """The encoder's (C, h, w) features for a grayscale (H, W) image."""
    return net.encoder(normalize_gray(torch.from_numpy(gray).float()[None, None]), stride)[0].numpy()


def coordinate_extent(coords: Sequence[np.ndarray]) -> float:
    """Diagonal of the 1st-99th percentile box of predicted coordinates: the scale the differences are judged
    against."""
    pts = np.concatenate([c.reshape(-1, 3) for c in coords])
    pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.size == 0:
        return float("nan")
    lo, hi = np.percentile(pts, [1, 99], axis=0)
    return float(np.linalg.norm(hi - lo))


def fp32_parity(
    net: SCRNetwork,
    fp32_path: Path,
    frames: Sequence[CheckFrame],
    progress: ProgressFn | None = None,
    stride: int = OUTPUT_STRIDE,
) -> dict:
    """Max |ONNX - torch| over the frames' coordinates, as metres and as a fraction of the scene extent; pose
    differences; and the same for the encoder features output (relative to their largest magnitude)."""
    sess = onnx_session(fp32_path)
    max_diff = 0.0
    feat_diff, feat_scale, has_features = 0.0, 0.0, False
    refs = []
    dt, dr = [], []
    for i, f in enumerate(frames):
        a = torch_coords(net, f.gray, stride)
        b, feats = onnx_outputs(sess, f.gray, features=True)
        refs.append(a)
        max_diff = max(max_diff, float(np.abs(a - b).max()))
        if feats is not None:
            ref_feats = torch_features(net, f.gray, stride)
            has_features = True
            feat_diff = max(feat_diff, float(np.abs(feats - ref_feats).max()))
            feat_scale = max(feat_scale, float(np.abs(ref_feats).max()))
        pa, pb = solve_from_grid(a, f.intrinsics, stride), solve_from_grid(b, f.intrinsics, stride)
        if pa.T_c2w is not None and pb.T_c2w is not None:
            t, r = pose_error(pb.T_c2w, pa.T_c2w)
            dt.append(t)
            dr.append(r)
        if progress:
            progress("check fp32", (i + 1) / len(frames), {"max_diff_m": max_diff})
    extent = coordinate_extent(refs)
    return {
        "frames": len(frames),
        "max_abs_diff_m": max_diff,
        "scene_extent_m": extent,
        "max_abs_diff_fraction": max_diff / extent if extent and np.isfinite(extent) else None,
        "pose_frames_compared": len(dt),
        "pose_max_translation_diff_m": max(dt) if dt else None,
        "pose_max_rotation_diff_deg": max(dr) if dr else None,
        "features_max_abs_diff": feat_diff if has_features else None,
        "features_max_abs": feat_scale if has_features else None,
    }


def localization_accuracy(
    model_path: Path,
    frames: Sequence[CheckFrame],
    label: str,
    progress: ProgressFn | None = None,
    stride: int = OUTPUT_STRIDE,
) -> dict:
    """accuracy_summary (without per-frame rows) of one ONNX model on posed frames."""
    sess = onnx_session(model_path)
    results = []
    for i, f in enumerate(frames):
        t0 = time.perf_counter()
        res = solve_from_grid(onnx_coords(sess, f.gray), f.intrinsics, stride)
        ms = (time.perf_counter() - t0) * 1000.0
        t_err, r_err = pose_error(res.T_c2w, f.pose) if res.T_c2w is not None else (float("inf"), float("inf"))
        results.append(FrameResult(f.name, res.localized, t_err, r_err, res.inliers, ms))
        if progress:
            progress(f"check {label}", (i + 1) / len(frames), {"frame": i + 1})
    s = accuracy_summary(results)
    s.pop("per_frame")
    return s
