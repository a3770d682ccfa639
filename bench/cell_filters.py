"""Would a per-cell filter computed without the true pose pick the test cells that are right? Two candidates,
each measured by the share of test cells within 4 px under the true pose and by the PnP pose's error:

- texture: the mean Sobel gradient magnitude of the network input around each cell (16 px box), cells split into
  quartiles; PnP on all cells, the most textured half, the most textured quarter;
- surface: the distance of each test cell's coordinate to the nearest trusted training cell (the map's own
  predictions on its training images that reproject within 2 px under their poses); PnP on the coordinates snapped to
  the mean of their 8 nearest trusted training points, and on the nearer half of the cells.

    python bench/cell_filters.py MAP SCENE [--json OUT]

bench/herz_gap.md has the figures.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from acesplat.core.atomic import write_json
from acesplat.core.geometry import pose_error
from acesplat.core.grid import cell_reprojection_errors, grid_correspondences
from acesplat.core.pnp import solve_pnp
from acesplat.core.scene import read_split
from acesplat.scr.localize import Localizer
from acesplat.scr.mapfile import encoder_for_map, load_map

GOOD_PX = 4.0
TRUSTED_PX = 2.0
TEXTURE_BOX = 16
NEIGHBOURS = 8


def cell_texture(gray: np.ndarray, grid_hw: tuple[int, int]) -> np.ndarray:
    """(h, w) mean gradient magnitude of a (H, W) uint8 image around each cell."""
    g = gray.astype(np.float32)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    return cv2.resize(cv2.blur(mag, (TEXTURE_BOX, TEXTURE_BOX)), grid_hw[::-1], interpolation=cv2.INTER_AREA)


def translation_cm(res, pose: np.ndarray) -> float:
    return 100.0 * pose_error(res.T_c2w, pose)[0] if res.T_c2w is not None else float("inf")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    m = load_map(args.map)
    loc = Localizer(m.network(encoder_for_map(m, args.map, None)), m.short_side, {})

    cloud = []
    for f in read_split(args.scene, "train").frames:
        gray, intr = loc.network_input(f.load_rgb(), f.intrinsics)
        c = loc.coordinates(gray)
        err = cell_reprojection_errors(c, f.pose, intr.K).reshape(-1)
        cloud.append(c.reshape(-1, 3)[err < TRUSTED_PX])
    cloud = np.concatenate(cloud)
    tree = cKDTree(cloud)
    print(f"trusted training cells: {len(cloud)}")

    rows = []
    for f in read_split(args.scene, "test").frames:
        gray, intr = loc.network_input(f.load_rgb(), f.intrinsics)
        c = loc.coordinates(gray)
        pts, pix = grid_correspondences(c)
        good = cell_reprojection_errors(c, f.pose, intr.K).reshape(-1) < GOOD_PX
        tex = cell_texture(gray, c.shape[:2]).reshape(-1)
        quart = np.digitize(tex, np.quantile(tex, [0.25, 0.5, 0.75]))
        dist, idx = tree.query(pts, k=NEIGHBOURS)
        snapped = cloud[idx].mean(axis=1)
        near = dist[:, 0] < np.median(dist[:, 0])
        row = {
            "frame": f.name,
            "good_share": float(good.mean()),
            "good_share_by_texture_quartile": [float(good[quart == q].mean()) for q in range(4)],
            "distance_m_good_bad": [float(np.median(dist[good, 0])), float(np.median(dist[~good, 0]))],
            "good_share_snapped": float(
                np.mean(cell_reprojection_errors(snapped.reshape(c.shape), f.pose, intr.K) < GOOD_PX)
            ),
            "pose_cm": {
                "all": translation_cm(solve_pnp(pix, pts, intr), f.pose),
                "textured_half": translation_cm(
                    solve_pnp(pix[tex >= np.median(tex)], pts[tex >= np.median(tex)], intr), f.pose
                ),
                "textured_quarter": translation_cm(solve_pnp(pix[quart == 3], pts[quart == 3], intr), f.pose),
                "snapped": translation_cm(solve_pnp(pix, snapped, intr), f.pose),
                "near_half": translation_cm(solve_pnp(pix[near], pts[near], intr), f.pose),
            },
        }
        rows.append(row)
        p = row["pose_cm"]
        print(
            f"{f.name[-12:]:>12s} good {row['good_share']:.3f} by texture "
            + " ".join(f"{x:.2f}" for x in row["good_share_by_texture_quartile"])
            + f" | snapped {row['good_share_snapped']:.3f} | pose cm "
            + " ".join(f"{k} {v:.2f}" for k, v in p.items()),
            flush=True,
        )
    keys = list(rows[0]["pose_cm"])
    med = {k: float(np.median([r["pose_cm"][k] for r in rows])) for k in keys}
    within = {k: int(sum(r["pose_cm"][k] <= 10.0 for r in rows)) for k in keys}
    quart = np.mean([r["good_share_by_texture_quartile"] for r in rows], axis=0)
    print("good share by texture quartile, low -> high: " + " ".join(f"{x:.3f}" for x in quart))
    print("median pose cm: " + ", ".join(f"{k} {v:.2f} ({within[k]}/{len(rows)} within 10 cm)" for k, v in med.items()))
    if args.json is not None:
        write_json(args.json, {"map": str(args.map), "scene": str(args.scene), "frames": rows, "median_cm": med})


if __name__ == "__main__":
    main()
