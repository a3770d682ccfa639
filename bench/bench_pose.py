"""Pose a folder with `acesplat pose` and score it against a ground-truth ACE scene (bench/pose.md).

    python bench/bench_pose.py IMAGES_DIR GT_SCENE OUT_SCENE [--matcher M] [--scale-from A B]

IMAGES_DIR holds the images (for a scene split in train/test, a folder of links to both); GT_SCENE's poses are matched
by file stem. With --scale-from the two cameras' true distance is passed to `acesplat pose`, and the scale error is
that of the similarity left between the metric poses and the truth. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from acesplat.core.geometry import apply_similarity, pose_error, rotation_angle_deg, similarity_align
from acesplat.core.machine import cpu_isa
from acesplat.core.scene import read_split


def truth(scene: Path) -> dict[str, np.ndarray]:
    out = {}
    for split in ("train", "test"):
        if (scene / split / "rgb").is_dir():
            out.update({f.name: f.pose for f in read_split(scene, split).frames})
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("images", type=Path)
    ap.add_argument("gt", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--matcher", default="sequential")
    ap.add_argument("--scale-from", nargs=2, default=None)
    args = ap.parse_args()
    gt = truth(args.gt)
    cli = [sys.executable, "-P", "-c", "from acesplat.apps.cli import main; main()"]
    cmd = cli + ["pose", str(args.images), "-o", str(args.out), "--matcher", args.matcher, "--test-every", "0"]
    cmd += ["--json", str(args.out) + ".json"]
    if args.scale_from:
        a, b = args.scale_from
        d = float(np.linalg.norm(gt[Path(a).stem][:3, 3] - gt[Path(b).stem][:3, 3]))
        cmd += ["--scale-from", a, b, f"{d:.9f}"]
    subprocess.run(cmd, check=True, env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})
    report = json.loads(Path(str(args.out) + ".json").read_text())
    frames = read_split(args.out, "train").frames
    names = [f.name.split("_", 1)[1] for f in frames]
    est = np.stack([f.pose for f in frames])
    ref = np.stack([gt[n] for n in names])
    s, R, t = similarity_align(est[:, :3, 3], ref[:, :3, 3])
    aligned = apply_similarity(s, R, t, est)
    errs = np.array([pose_error(a, g) for a, g in zip(aligned, ref)])
    order = np.argsort(names)
    rel = [
        rotation_angle_deg((est[i, :3, :3].T @ est[j, :3, :3]).T @ (ref[i, :3, :3].T @ ref[j, :3, :3]))
        for i, j in zip(order[:-1], order[1:])
    ]
    length = float(np.linalg.norm(np.diff(ref[order, :3, 3], axis=0), axis=1).sum())
    row = {
        "images": report["images"],
        "registered": report["registered"],
        "points": report["points"],
        "reproj_px": report["mean_reprojection_error_px"],
        "trajectory_m": length,
        "pos_median_m": float(np.median(errs[:, 0])),
        "pos_max_m": float(errs[:, 0].max()),
        "pos_max_frac": float(errs[:, 0].max() / length),
        "rot_median_deg": float(np.median(errs[:, 1])),
        "rot_max_deg": float(errs[:, 1].max()),
        "rel_rot_max_deg": float(max(rel)),
        "units": report["units"],
        "scale_error": abs(s - 1.0) if report["units"] == "metres" else None,
        "seconds": report["seconds"],
        "phase_seconds": report["phase_seconds"],
        "isa": cpu_isa(),
    }
    print(json.dumps(row))


if __name__ == "__main__":
    main()
