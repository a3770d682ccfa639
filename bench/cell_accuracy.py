"""How well a map's scene coordinates hold on views it was not trained on: each cell's reprojection error under
the true pose.

On a 7-frame test split the median pose error moves by centimetres between runs of one recipe
(bench/herz_gap.md). The share of cells whose predicted coordinate projects within a few pixels of the
cell, over thousands of cells per frame, is the steadier signal for comparing recipes, and the gap between
the training and the test split says whether the fit or the generalisation limits.

    python bench/cell_accuracy.py MAP SCENE [--splits test,train] [--frames 7] [--json OUT]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from acesplat.core.atomic import write_json
from acesplat.core.geometry import pose_error
from acesplat.core.grid import cell_reprojection_errors
from acesplat.core.pnp import solve_from_grid
from acesplat.core.scene import read_split
from acesplat.scr.localize import Localizer
from acesplat.scr.mapfile import encoder_for_map, load_map

THRESHOLDS_PX = (1.0, 2.0, 4.0, 10.0)


def split_cell_accuracy(split, loc: Localizer, max_frames: int = 0) -> list[dict]:
    """Per frame of ``split`` (at most ``max_frames``, evenly spaced; 0 = all): the share of cells within each of
    THRESHOLDS_PX under the true pose, and the stride-8 pose's translation error (cm; inf when not solved)."""
    frames = split.frames
    if max_frames and len(frames) > max_frames:
        frames = [frames[i] for i in np.linspace(0, len(frames) - 1, max_frames).round().astype(int)]
    rows = []
    for f in frames:
        coords, intr = loc.predict(f.load_rgb(), f.intrinsics)
        err = cell_reprojection_errors(coords, f.pose, intr.K)
        res = solve_from_grid(coords, intr)
        t_cm = 100.0 * pose_error(res.T_c2w, f.pose)[0] if res.T_c2w is not None else float("inf")
        rows.append(
            {
                "frame": f.name,
                "within_px": [float(np.mean(err < t)) for t in THRESHOLDS_PX],
                "pose_translation_cm": t_cm,
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("map", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--splits", default="test,train")
    ap.add_argument("--frames", type=int, default=0, help="At most this many frames per split, evenly spaced (0: all).")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    m = load_map(args.map)
    loc = Localizer(m.network(encoder_for_map(m, args.map, None)), m.short_side, {})
    report: dict = {"map": str(args.map), "scene": str(args.scene), "thresholds_px": list(THRESHOLDS_PX)}
    print(
        f"{'split':>5s} {'frame':>16s} "
        + " ".join(f"{'<' + format(t, 'g') + ' px':>7s}" for t in THRESHOLDS_PX)
        + f" {'pose cm':>8s}"
    )
    for name in args.splits.split(","):
        rows = split_cell_accuracy(read_split(args.scene, name), loc, args.frames)
        for r in rows:
            print(
                f"{name:>5s} {r['frame'][-16:]:>16s} "
                + " ".join(f"{s:7.3f}" for s in r["within_px"])
                + f" {r['pose_translation_cm']:8.2f}"
            )
        mean = np.mean([r["within_px"] for r in rows], axis=0)
        print(
            f"{name:>5s} {'mean':>16s} "
            + " ".join(f"{s:7.3f}" for s in mean)
            + f" {np.mean([r['pose_translation_cm'] for r in rows]):8.2f}"
        )
        report[name] = {"frames": rows, "mean_within_px": mean.tolist()}
    if args.json:
        write_json(args.json, report)


if __name__ == "__main__":
    main()
