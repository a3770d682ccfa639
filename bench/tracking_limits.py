"""The tracking limit (TrackingConfig.max_motion_m / max_motion_deg) on the replayed test splits: how each frame's pose
was made and its accuracy, for each limit, as `acesplat-edge replay BUNDLE SCENE --int8` runs them (frames in order,
as fast as possible).

    PYTHONPATH=. python -P bench/tracking_limits.py BUNDLE:SCENE [BUNDLE:SCENE ...] [--limits 0.15,10:0.25,15]
        [--precision int8]
"""

from __future__ import annotations

import argparse
import gc

from acesplat.core.bundle import load_bundle
from edge.replay import replay_split
from edge.runtime import EdgeLocalizer
from edge.tracking import TrackingConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="BUNDLE:SCENE")
    ap.add_argument("--limits", default="0.15,10:0.25,15", help="M,DEG pairs separated by ':'")
    ap.add_argument("--precision", default="int8")
    ap.add_argument("--split", default="test")
    a = ap.parse_args()
    print("| scene | limit | within 5 cm / 5 deg | median | tracked / scr / re-anchors | fallbacks | resets |")
    print("|---|---|---|---|---|---|---|")
    for pair in a.pairs:
        bundle_path, scene = pair.split(":")
        bundle = load_bundle(bundle_path)
        for lim in a.limits.split(":"):
            m, deg = (float(x) for x in lim.split(","))
            loc = EdgeLocalizer(bundle, a.precision, tracking=TrackingConfig(max_motion_m=m, max_motion_deg=deg))
            s = replay_split(loc, scene, a.split)
            del loc
            gc.collect()
            print(
                f"| {scene} | {m:g} m, {deg:g} deg | {s['recall_5cm_5deg']:.1f}% | "
                f"{100 * s['median_translation_m']:.2f} cm / {s['median_rotation_deg']:.3f} deg | "
                f"{s['tracked']} / {s['scr']} / {s['reanchors']} | {s['fallback_reasons']} | {s['resets']} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
