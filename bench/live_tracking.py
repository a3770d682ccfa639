"""Tracking on a live source: a posed split replayed at a camera's rate (latest frame wins, drops counted), the loop
sequential or overlapped, per INT8 graph; frames localized, dropped, how each pose was made, accuracy, poses a second.

    PYTHONPATH=. python -P bench/live_tracking.py BUNDLE SCENE [--split train] [--fps 30] [--precisions int8,int8_vnni]
        [--loops sequential,overlapped] [--repeats 2] [--max-motion M,DEG] [--json OUT]

The split's images, poses and calibrations are linked into a temporary folder with a ``timestamps.txt`` at ``fps``
(the split's own timestamps are not needed), then replayed with ``realtime`` as `acesplat-edge localize --source
replay:DIR --realtime` does. Accuracy counts the frames that were localized (a dropped frame has no pose).
"""

from __future__ import annotations

import argparse
import collections
import gc
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from acesplat.core.bundle import load_bundle
from acesplat.core.geometry import pose_error
from acesplat.core.pose import TrackingState
from acesplat.core.scene import split_folder
from edge.inference import runtime_info
from edge.loop import overlap_threads, run_loop
from edge.runtime import EdgeLocalizer
from edge.sources import SourceOptions, open_source
from edge.tracking import TrackingConfig


def timed_copy(split: Path, out: Path, fps: float) -> int:
    """``split``'s rgb, poses and calibration linked into ``out`` with timestamps at ``fps``; the frame count."""
    out.mkdir(parents=True)
    for sub in ("rgb", "poses", "calibration"):
        if (split / sub).is_dir():
            (out / sub).symlink_to((split / sub).resolve())
    n = len(list((split / "rgb").iterdir()))
    (out / "timestamps.txt").write_text("".join(f"{i / fps:.6f}\n" for i in range(n)))
    return n


def one_run(bundle, folder: Path, precision: str, loop: str, tracking: TrackingConfig) -> dict:
    overlap = loop == "overlapped"
    loc = EdgeLocalizer(bundle, precision, overlap_threads() if overlap else None, tracking=tracking)
    src = open_source(f"replay:{folder}", SourceOptions(input_size=bundle.input_size, realtime=True))
    outs = []
    stats = run_loop(src, loc, outs.append, overlap=overlap)
    del loc
    gc.collect()
    errs = [pose_error(o.record.T_c2w, o.gt_pose) for o in outs if o.record.state == TrackingState.TRACKING]
    good = sum(t < 0.05 and r < 5.0 for t, r in errs)
    return {
        "frames": stats.frames,
        "dropped": stats.dropped,
        "poses_per_s": stats.fps,
        "modes": dict(collections.Counter(o.mode for o in outs)),
        "fallbacks": dict(collections.Counter(o.fallback for o in outs if o.fallback)),
        "within_5cm_5deg": good / max(1, stats.frames),
        "median_cm": 100.0 * float(np.median([t for t, _ in errs])) if errs else float("nan"),
        "resets": sum(o.reset for o in outs),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle")
    ap.add_argument("scene")
    ap.add_argument("--split", default="train")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--precisions", default="int8,int8_vnni")
    ap.add_argument("--loops", default="sequential,overlapped")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--max-motion", default=None, help="M,DEG: TrackingConfig.max_motion_m and max_motion_deg")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    bundle = load_bundle(a.bundle)
    tracking = TrackingConfig()
    if a.max_motion:
        m, deg = (float(x) for x in a.max_motion.split(","))
        tracking = TrackingConfig(max_motion_m=m, max_motion_deg=deg)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / a.split
        n = timed_copy(split_folder(a.scene, a.split, need_poses=True), folder, a.fps)
        for r in range(a.repeats):
            for precision in a.precisions.split(","):
                for loop in a.loops.split(","):
                    run = one_run(bundle, folder, precision, loop, tracking)
                    res = {"precision": precision, "loop": loop, "repeat": r, **run}
                    rows.append(res)
                    print(
                        f"{precision:9s} {loop:10s} #{r}: {res['frames']}/{n} localized, {res['dropped']} dropped, "
                        f"{res['poses_per_s']:.1f} poses/s, {res['within_5cm_5deg']:.1%} of the frames within 5 cm / "
                        f"5 deg (median {res['median_cm']:.2f} cm), modes {res['modes']}, fallbacks "
                        f"{res['fallbacks']}, resets {res['resets']}",
                        flush=True,
                    )
    info = runtime_info("cpu")
    print(f"onnxruntime {info['onnxruntime']}, ISA {' '.join(info['cpu_isa'])}; {n} frames at {a.fps:g} fps")
    if a.json:
        a.json.write_text(json.dumps({"runs": rows, "fps": a.fps, **info}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
