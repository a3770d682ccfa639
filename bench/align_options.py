"""Keyframe alignment options measured against each other on one map, interleaved frame by frame (bench/align.md).

Each test frame is localized once (SCR + PnP); then every option aligns that same pose, in an order rotated per
frame and repeat, so the machine's load hits all options alike. Only the alignment is timed.

    PYTHONPATH=. python -P bench/align_options.py MAP SCENE [--frames N] [--repeats R] [--only a,b] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from functools import partial

import numpy as np

from acesplat.align.flow_pnp import DENSE_ALIGN, KEYFRAME_ALIGN
from acesplat.align.keyframe_align import align_scr_pose
from acesplat.core.geometry import pose_error
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.core.machine import cpu_isa, machine_line
from acesplat.core.scene import read_split
from acesplat.scr.keyframes import MapKeyframes
from acesplat.scr.localize import Localizer
from acesplat.scr.mapfile import encoder_for_map, load_map

FULL = replace(DENSE_ALIGN, rounds=3, first_flow_scale=1.0, max_pairs=0, thinning="even", enough_pairs=0)
"""Every keyframe (4), three full-size rounds, every pair: the alignment before its cheaper defaults. The options
'dense', 'query*', 'cap*', 'enough*', 'default_*' (named when the dense matcher was the default), 'thr2' and 'step*'
are the dense matcher's (DENSE_ALIGN); 'default' and 'sparse_*' the sparse matcher's (KEYFRAME_ALIGN)."""
OPTIONS = {
    "base": FULL,
    "dense": DENSE_ALIGN,
    "default": KEYFRAME_ALIGN,
    "query": replace(DENSE_ALIGN, warp="query"),
    "cap2k_even": replace(FULL, max_pairs=2000),
    "cap5k_even": replace(FULL, max_pairs=5000),
    "cap2k_conf": replace(FULL, max_pairs=2000, thinning="confidence"),
    "dis_fast": replace(FULL, flow_preset="fast"),
    "coarse_first": replace(FULL, first_flow_scale=0.5),
    "early_exit": replace(FULL, converged_m=1e-3, converged_deg=0.01),
    "enough_8k": replace(FULL, enough_pairs=8000),
    "two_rounds": replace(FULL, rounds=2),
    "cap2k+early": replace(FULL, max_pairs=2000, converged_m=1e-3, converged_deg=0.01),
    "enough8k_r2": replace(FULL, enough_pairs=8000, rounds=2),
    "enough16k_r2": replace(FULL, enough_pairs=16000, rounds=2),
    "enough16k_r2_cap5k": replace(FULL, enough_pairs=16000, rounds=2, max_pairs=5000, thinning="confidence"),
    "r2_cap5k": replace(FULL, rounds=2, max_pairs=5000, thinning="confidence"),
    "default_16k": replace(DENSE_ALIGN, enough_pairs=16000),
    "default_32k": replace(DENSE_ALIGN, enough_pairs=32000),
    "default_32k_r3": replace(DENSE_ALIGN, enough_pairs=32000, rounds=3),
    "default_16k_r3": replace(DENSE_ALIGN, enough_pairs=16000, rounds=3),
    "query_r1": replace(DENSE_ALIGN, warp="query", rounds=1, first_flow_scale=1.0),
    "query_k2": replace(DENSE_ALIGN, warp="query"),
    "query_k2_r1": replace(DENSE_ALIGN, warp="query", rounds=1, first_flow_scale=1.0),
    "query_k1": replace(DENSE_ALIGN, warp="query"),
    "query_k2_half": replace(DENSE_ALIGN, warp="query", rounds=1, first_flow_scale=0.5),
    "thr2": replace(DENSE_ALIGN, threads=2),
    "step4": replace(DENSE_ALIGN, warp_step_px=4),
    "step2": replace(DENSE_ALIGN, warp_step_px=2),
    "step4_thr2": replace(DENSE_ALIGN, warp_step_px=4, threads=2),
    "sparse_r2": replace(KEYFRAME_ALIGN, rounds=2),
    "sparse_r3": replace(KEYFRAME_ALIGN, rounds=3),
    "sparse_2k": replace(KEYFRAME_ALIGN, corners=2000),
    "sparse_1k5": replace(KEYFRAME_ALIGN, corners=1500),
    "sparse_400": replace(KEYFRAME_ALIGN, corners=400),
    "sparse_t1": replace(KEYFRAME_ALIGN, threads=1),
    "sparse_noplane": replace(KEYFRAME_ALIGN, lk_plane_warp=False),
    "sparse_w15": replace(KEYFRAME_ALIGN, lk_window_px=15),
    "sparse_w11": replace(KEYFRAME_ALIGN, lk_window_px=11),
    "sparse_w21": replace(KEYFRAME_ALIGN, lk_window_px=21),
    "sparse_w31": replace(KEYFRAME_ALIGN, lk_window_px=31),
    "sparse_k6": replace(KEYFRAME_ALIGN),
    "sparse_k8": replace(KEYFRAME_ALIGN),
    "sparse_px2": replace(KEYFRAME_ALIGN, reproj_px=2.0),
    "sparse_fb1": replace(KEYFRAME_ALIGN, max_fb_error_px=1.0),
    "sparse_fb02": replace(KEYFRAME_ALIGN, max_fb_error_px=0.2),
}
KEYFRAME_COUNT = {
    "query_k2": 2,
    "query_k2_r1": 2,
    "query_k1": 1,
    "query_k2_half": 2,
    "sparse_k6": 6,
    "sparse_k8": 8,
}
"""Options that align to fewer than acesplat.align.keyframe_align.KEYFRAMES keyframes (nearest first)."""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("map")
    ap.add_argument("scene")
    ap.add_argument("--frames", type=int, default=0, help="every k-th test frame so that about this many run")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--only", default="", help="comma-separated option names (base always runs)")
    ap.add_argument("--json", default="")
    a = ap.parse_args()
    names = list(OPTIONS) if not a.only else ["base"] + [n for n in a.only.split(",") if n != "base"]
    m = load_map(a.map)
    net = m.network(encoder_for_map(m, a.map, None))
    kfs = MapKeyframes(read_split(a.scene, "train"), net, m.short_side)
    kfs.prepare()
    kfs.prepare_corners(KEYFRAME_ALIGN.corners)  # made on first use otherwise, inside the first frames' times
    loc = Localizer(net, m.short_side, {}, keyframes=None)
    frames = read_split(a.scene, "test").frames
    if a.frames and len(frames) > a.frames:
        frames = frames[:: int(np.ceil(len(frames) / a.frames))]
    rows: dict[str, dict[str, list]] = {n: {"t": [], "r": [], "ms": [], "status": []} for n in names}
    scr_err = []
    for fi, f in enumerate(frames):
        gray, intr = loc.network_input(f.load_rgb(), f.intrinsics)
        coords = loc.coordinates(gray)
        res = loc.localize(f.load_rgb(), f.intrinsics)
        if not res.localized or res.T_c2w is None:
            continue
        scr_err.append(pose_error(res.T_c2w, f.pose))
        for rep in range(a.repeats):
            k = (fi + rep) % len(names)
            for n in names[k:] + names[:k]:
                t0 = time.perf_counter()
                near = kfs.near if n not in KEYFRAME_COUNT else partial(kfs.near, k=KEYFRAME_COUNT[n])
                al = align_scr_pose(gray, intr, coords, OUTPUT_STRIDE, res.T_c2w, near, OPTIONS[n])
                ms = 1000.0 * (time.perf_counter() - t0)
                dt, dr = pose_error(al.pose, f.pose)
                r = rows[n]
                r["ms"].append(ms)
                if rep == 0:
                    r["t"].append(dt)
                    r["r"].append(dr)
                    r["status"].append(al.status)
    base_ms = np.array(rows["base"]["ms"])
    out = {
        "frames": len(scr_err),
        "scr_median_cm": 100 * float(np.median([e[0] for e in scr_err])),
        "machine": machine_line(),
        "cpu_isa": cpu_isa(),
    }
    print(out["machine"])
    print(f"{len(scr_err)} frames; SCR alone median {out['scr_median_cm']:.2f} cm")
    cols = ("med cm", "p90 cm", "max cm", "med deg", "mean ms", "ratio")
    print(f"{'option':20s} " + " ".join(f"{c:>8s}" for c in cols) + "  statuses")
    for n in names:
        r = rows[n]
        t, ms = np.array(r["t"]) * 100, np.array(r["ms"])
        ratio = float(np.median(ms / base_ms))
        st = {s: r["status"].count(s) for s in sorted(set(r["status"]))}
        out[n] = {
            "median_cm": float(np.median(t)),
            "p90_cm": float(np.percentile(t, 90)),
            "max_cm": float(t.max()),
            "median_deg": float(np.median(r["r"])),
            "mean_ms": float(ms.mean()),
            "ms_ratio_to_base": ratio,
            "statuses": st,
        }
        print(
            f"{n:20s} {np.median(t):8.2f} {np.percentile(t, 90):8.2f} {t.max():8.2f} {np.median(r['r']):8.3f} "
            f"{ms.mean():8.1f} {ratio:8.2f}  {st}"
        )
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)


if __name__ == "__main__":
    main()
