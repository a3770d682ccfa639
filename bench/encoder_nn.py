"""How distinctive are the encoder's features in one scene, independent of any head training?

For every test cell of the built-in scene, the nearest training cell in feature space (cosine) is looked
up, and the true scene coordinates of the two (from the rendered depth) are compared. If most test cells
find a training cell within a few centimetres, the features already tell the surfaces apart, and whatever
error a mapped head shows comes from the head's fit, not from the encoder. Prints the fraction of test cells
within 5 / 10 / 25 cm and the median distance, for each encoder given, plus the machine. With
``--train-scales`` the training images are also encoded rescaled (as ACE's mapping augmentation does), which
shows how far the features are from scale-invariant.

    python bench/encoder_nn.py [--scene runs/bench_stage1/synth] [--encoder PATH ...] [--every 3] \
        [--train-scales 1,0.667,1.5]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from acesplat.core.grid import cell_centers
from acesplat.core.machine import machine_line
from acesplat.core.preprocess import size_for_short_side, to_gray_input
from acesplat.core.scene import SceneSplit, read_split
from acesplat.scr.encoders import load_encoder
from acesplat.scr.network import Encoder, normalize_gray
from acesplat.synth import synthesize

ROOT = Path(__file__).resolve().parents[1]


@torch.no_grad()
def cell_features(encoder: Encoder, split: SceneSplit, short_side: int, every: int) -> tuple[torch.Tensor, np.ndarray]:
    """Unit features (N, C) and true world coordinates (N, 3) of every cell with depth, every ``every``-th frame."""
    feats, coords = [], []
    for frame in split.frames[::every]:
        rgb = frame.load_rgb()
        gray, intr = to_gray_input(rgb, frame.intrinsics, size_for_short_side(rgb.shape[0], rgb.shape[1], short_side))
        f = encoder(normalize_gray(torch.from_numpy(gray)[None, None]))[0]
        c, gh, gw = f.shape
        depth = frame.load_depth()
        centres = cell_centers(gh, gw)
        # Depth at the cell centre, looked up in the (possibly larger) depth map.
        u = np.clip((centres[:, 0] * depth.shape[1] / intr.width).astype(int), 0, depth.shape[1] - 1)
        v = np.clip((centres[:, 1] * depth.shape[0] / intr.height).astype(int), 0, depth.shape[0] - 1)
        z = depth[v, u].astype(np.float64)
        ok = z > 0
        X = intr.unproject(centres[ok], z[ok]) @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        feats.append(f.reshape(c, -1).T[torch.from_numpy(ok)])
        coords.append(X)
    return torch.nn.functional.normalize(torch.cat(feats), dim=1), np.concatenate(coords)


def nearest_distances(
    train_f: torch.Tensor, train_x: np.ndarray, test_f: torch.Tensor, test_x: np.ndarray
) -> np.ndarray:
    """Distance (M,) from each test cell's true point to the true point of its nearest training feature."""
    out = []
    for i in range(0, len(test_f), 2048):
        j = (test_f[i : i + 2048] @ train_f.T).argmax(dim=1).numpy()
        out.append(np.linalg.norm(train_x[j] - test_x[i : i + 2048], axis=1))
    return np.concatenate(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", type=Path, default=ROOT / "runs" / "bench_stage1" / "synth")
    ap.add_argument(
        "--encoder", type=Path, action="append", default=None, help="Encoder weights (repeatable; default: shipped)."
    )
    ap.add_argument("--short-side", type=int, default=240)
    ap.add_argument("--every", type=int, default=3, help="Use every n-th test frame.")
    ap.add_argument("--train-scales", default="1", help="Comma-separated scales of the training images' short side.")
    args = ap.parse_args()
    if not (args.scene / "train").is_dir():
        synthesize(args.scene, seed=0, overwrite=True)
    train, test = read_split(args.scene, "train"), read_split(args.scene, "test")
    print(machine_line())
    print(
        f"scene {args.scene}: {len(train)} training frames (all cells), one in {args.every} of {len(test)} test frames"
    )
    for path in args.encoder or [None]:
        t0 = time.perf_counter()
        enc, ident = load_encoder(path)
        enc.eval()
        qf, qx = cell_features(enc, test, args.short_side, args.every)
        for scale in (float(s) for s in args.train_scales.split(",")):
            tf, tx = cell_features(enc, train, round(args.short_side * scale), 1)
            d = nearest_distances(tf, tx, qf, qx)
            print(
                f"{ident.name:24s} train x{scale:<5.3g} test cells {len(d):6d} vs {len(tf):6d}: within 5 cm "
                f"{100 * np.mean(d < 0.05):5.1f}%  "
                f"10 cm {100 * np.mean(d < 0.10):5.1f}%  25 cm {100 * np.mean(d < 0.25):5.1f}%  median "
                f"{100 * np.median(d):5.1f} cm  "
                f"({time.perf_counter() - t0:.0f} s)"
            )


if __name__ == "__main__":
    main()
