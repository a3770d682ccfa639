"""Per-frame pose differences between two runs over the same frames (`acesplat eval` or `acesplat-edge replay`
JSONs, whose per_frame records carry each estimate's pose_c2w): e.g. INT8 against FP32 on one machine.

    python -P bench/pose_diff.py FP32.json INT8.json [--json OUT]

Prints each frame's difference (cm, deg) and both runs' errors against the true pose, then the median and the
largest difference over the frames both runs localized.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from acesplat.core.geometry import pose_error


def frames(path: str) -> dict[str, dict]:
    with open(path) as fh:
        return {f["name"]: f for f in json.load(fh)["per_frame"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    a, b = frames(args.a), frames(args.b)
    rows = []
    print(f"{'frame':14s} {'diff cm':>8s} {'diff deg':>9s} {'A err cm':>9s} {'B err cm':>9s}")
    for name in sorted(set(a) & set(b)):
        fa, fb = a[name], b[name]
        if not (fa["localized"] and fb["localized"]) or fa.get("pose_c2w") is None or fb.get("pose_c2w") is None:
            print(f"{name:14s} {'-':>8s} {'-':>9s}  (localized: {fa['localized']} / {fb['localized']})")
            continue
        dt, dr = pose_error(np.array(fb["pose_c2w"]), np.array(fa["pose_c2w"]))
        rows.append(
            {"name": name, "diff_m": dt, "diff_deg": dr, "a_m": fa["translation_m"], "b_m": fb["translation_m"]}
        )
        print(f"{name:14s} {100 * dt:8.3f} {dr:9.4f} {100 * fa['translation_m']:9.2f} {100 * fb['translation_m']:9.2f}")
    if not rows:
        raise SystemExit("no frame localized in both runs")
    t = np.array([r["diff_m"] for r in rows])
    d = np.array([r["diff_deg"] for r in rows])
    out = {
        "a": args.a,
        "b": args.b,
        "frames": len(rows),
        "median_diff_cm": 100 * float(np.median(t)),
        "max_diff_cm": 100 * float(t.max()),
        "median_diff_deg": float(np.median(d)),
        "max_diff_deg": float(d.max()),
        "per_frame": rows,
    }
    print(
        f"{len(rows)} frames: median {out['median_diff_cm']:.3f} cm / {out['median_diff_deg']:.4f} deg, "
        f"max {out['max_diff_cm']:.3f} cm / {out['max_diff_deg']:.4f} deg"
    )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=2)


if __name__ == "__main__":
    main()
