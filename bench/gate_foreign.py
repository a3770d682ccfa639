"""The tracking gate on true, foreign and synthetic bad frames (bench/gate.md).

    collect: PYTHONPATH=. python bench/gate_foreign.py collect MAP SCENE --foreign SCENE2 SCENE3 --out RAW.npz
             [--short-side 240]   (the network smaller than the map's side, as the edge's --align runs it)
    report:  PYTHONPATH=. python bench/gate_foreign.py report RAW1.npz RAW2.npz ...

``collect`` localizes, with a map, the own scene's test split (true frames), every image of the foreign scenes
resized to the own images' size and seen through the own test camera, and synthetic bad versions of the true
frames (blank, dark, saturated, blurred, mirrored). It stores each frame's predicted grid, PnP pose and the
intrinsics, so ``report`` can evaluate any GateConfig without running the network again.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from acesplat.core.gate import GateConfig, gate_grid, mirror_frame, mirror_result, needs_mirror_check
from acesplat.core.pnp import PnPConfig, PnPResult, solve_from_grid

SYNTH = ("blank", "dark", "saturated", "blurred", "mirrored")


def synthetic(rgb: np.ndarray, kind: str) -> np.ndarray:
    """A bad version (H, W, 3) uint8 of an RGB frame."""
    if kind == "blank":
        return np.full_like(rgb, 128)
    if kind == "dark":
        return (rgb.astype(np.float32) * 0.03).astype(np.uint8)
    if kind == "saturated":
        return np.clip(rgb.astype(np.float32) * 4.0 + 60.0, 0, 255).astype(np.uint8)
    if kind == "blurred":
        s = max(rgb.shape[:2]) / 40.0
        return cv2.GaussianBlur(rgb, (0, 0), s)
    if kind == "mirrored":
        return np.ascontiguousarray(rgb[:, ::-1])
    raise ValueError(kind)


def collect(args: argparse.Namespace) -> None:
    import torch

    from acesplat.core.scene import read_split
    from acesplat.scr.localize import Localizer
    from acesplat.scr.mapfile import encoder_for_map, load_map

    torch.set_num_threads(1)
    m = load_map(args.map)
    loc = Localizer(m.network(encoder_for_map(m, args.map)), args.short_side or m.short_side, {})
    test = read_split(args.scene, "test")
    H, W = test.frames[0].load_rgb().shape[:2]
    cam = test.frames[0].intrinsics
    rows: list[tuple[str, str, np.ndarray, object]] = []
    for f in test.frames:
        rgb = f.load_rgb()
        rows.append(("true", f.name, rgb, f.intrinsics))
    for f in test.frames[:: args.synth_every]:
        rgb = f.load_rgb()
        for k in SYNTH:
            rows.append((k, f.name, synthetic(rgb, k), f.intrinsics))
    for scene in args.foreign:
        for split in ("train", "test"):
            fr = read_split(scene, split).frames[:: args.foreign_every]
            for f in fr:
                rgb = cv2.resize(f.load_rgb(), (W, H), interpolation=cv2.INTER_AREA)
                rows.append(("foreign", f"{Path(scene).name}/{split}/{f.name}", rgb, cam))
    coords, poses, Ks, kinds, names, sizes, ms, mcoords, mKs = [], [], [], [], [], [], [], [], []
    for i, (kind, name, rgb, intr) in enumerate(rows):
        t0 = time.perf_counter()
        gray, ni = loc.network_input(rgb, intr)
        c = loc.coordinates(gray)
        res = solve_from_grid(c, ni, config=PnPConfig())
        ms.append((time.perf_counter() - t0) * 1000)
        m_gray, m_intr = mirror_frame(gray, ni)  # the mirror check's input, for report to apply it
        mcoords.append(loc.coordinates(m_gray).astype(np.float32))
        mKs.append([m_intr.fx, m_intr.fy, m_intr.cx, m_intr.cy, m_intr.width, m_intr.height])
        coords.append(c.astype(np.float32))
        poses.append(res.T_c2w if res.T_c2w is not None else np.full((4, 4), np.nan))
        Ks.append([ni.fx, ni.fy, ni.cx, ni.cy, ni.width, ni.height])
        kinds.append(kind)
        names.append(name)
        sizes.append(res.inliers)
        if i % 20 == 0:
            print(f"{i}/{len(rows)} {kind} {name} inliers {res.inliers}", flush=True)
    np.savez_compressed(
        args.out,
        map=str(args.map),
        coords=np.stack(coords),
        poses=np.stack(poses),
        K=np.array(Ks),
        kinds=np.array(kinds),
        names=np.array(names),
        gt=np.stack([f.pose for f in test.frames]),
        ms=np.array(ms),
        mcoords=np.stack(mcoords),
        mK=np.array(mKs),
    )
    print(f"wrote {args.out}: {len(rows)} frames")


def verdicts(raw: dict, gate: GateConfig, pnp: PnPConfig) -> list[dict]:
    """Per frame: kind, name, the verdict's fields and whether the old fixed count said TRACKING."""
    from acesplat.core.camera import Intrinsics

    out = []
    for i, (c, T, k, kind, name) in enumerate(zip(raw["coords"], raw["poses"], raw["K"], raw["kinds"], raw["names"])):
        intr = Intrinsics(k[0], k[1], k[2], k[3], int(k[4]), int(k[5]))
        pose = None if np.isnan(T).any() else T
        v = gate_grid(c, intr, pose, pnp.threshold_px, config=gate, min_inliers=pnp.min_inliers)
        res = PnPResult(pose, v.inliers, v.valid, v.passed, v)
        if "mcoords" in raw and needs_mirror_check(res, gate):
            mk = raw["mK"][i]
            m_intr = Intrinsics(mk[0], mk[1], mk[2], mk[3], int(mk[4]), int(mk[5]))
            v = mirror_result(res, raw["mcoords"][i], m_intr, pnp, config=gate).gate
        d = v.as_dict()
        d.update(kind=str(kind), name=str(name), old=pose is not None and v.inliers >= pnp.min_inliers)
        out.append(d)
    return out


def report(args: argparse.Namespace) -> None:
    from acesplat.core.geometry import pose_error

    gate = GateConfig(**json.loads(args.gate)) if args.gate else GateConfig()
    gate_off = replace(gate, min_score=0.0, min_ratio=0.0, min_coverage=0.0, max_residual=1.0)
    pnp = PnPConfig()
    print(f"gate: {gate}")
    print(
        "| map | frames | n | TRACKING (fixed 50) | TRACKING (gate) | max score | max inliers | max ratio "
        "| LOST by the mirror check | score over the mirror's (true: min; others: max) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    worst_foreign = 0.0
    for path in args.raw:
        raw = dict(np.load(path, allow_pickle=False))
        vs = verdicts(raw, gate, pnp)
        off = verdicts(raw, gate_off, pnp)
        label = Path(str(raw["map"])).name
        gt = {}
        true_i = [i for i, v in enumerate(vs) if v["kind"] == "true"]
        for j, i in enumerate(true_i):
            gt[i] = raw["gt"][j]
        for kind in ("true", *SYNTH, "foreign"):
            idx = [i for i, v in enumerate(vs) if v["kind"] == kind]
            if not idx:
                continue
            old = sum(off[i]["old"] for i in idx)
            new = sum(vs[i]["passed"] for i in idx)
            ms = max(vs[i]["score"] for i in idx)
            mi = max(vs[i]["inliers"] for i in idx)
            mr = max(vs[i]["ratio"] for i in idx)
            checked = [i for i in idx if vs[i]["mirror_score"] is not None]
            by_mirror = sum(not vs[i]["passed"] and vs[i]["reasons"][-1].startswith("the mirrored") for i in checked)
            over = [vs[i]["score"] / max(vs[i]["mirror_score"], 1e-9) for i in checked]
            over_s = "-" if not over else f"{(min(over) if kind == 'true' else max(over)):.2f} ({len(over)} checked)"
            extra = ""
            if kind == "true":
                ok5 = 0
                for i in idx:
                    T = raw["poses"][i]
                    if vs[i]["passed"] and not np.isnan(T).any():
                        t, r = pose_error(T, gt[i])
                        ok5 += t < 0.05 and r < 5.0
                lo = min(vs[i]["score"] for i in idx if off[i]["old"]) if old else float("nan")
                extra = f" (5cm/5deg among TRACKING: {ok5}; min score of the fixed-50 TRACKING: {lo:.3f})"
            else:
                worst_foreign = max(worst_foreign, ms)
            print(
                f"| {label} | {kind}{extra} | {len(idx)} | {old} | {new} | {ms:.3f} | {mi} | {mr:.3f} "
                f"| {by_mirror} | {over_s} |"
            )
        if args.verbose:
            for v in vs:
                print(
                    f"  {v['kind']:9s} {v['name']:40s} in {v['inliers']:5d} ratio {v['ratio']:.3f} "
                    f"cov {v['coverage']:.2f} hull {v['hull']:.2f} res {v['residual']:.2f} score {v['score']:.3f} "
                    f"{'TRACK' if v['passed'] else 'LOST'} {'old-TRACK' if v['old'] else ''}"
                    + (f" mirror {v['mirror_score']:.3f}" if v["mirror_score"] is not None else "")
                )
    print(f"largest non-true score {worst_foreign:.3f} (threshold {gate.min_score}, half {gate.min_score / 2})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect")
    c.add_argument("map", type=Path)
    c.add_argument("scene", type=Path)
    c.add_argument("--foreign", type=Path, nargs="+", default=[])
    c.add_argument("--foreign-every", type=int, default=1, help="Every n-th image of a foreign split.")
    c.add_argument("--synth-every", type=int, default=1, help="Synthetic bad frames of every n-th true frame.")
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--short-side", type=int, default=0, help="Network input's shorter side (0: the map's).")
    r = sub.add_parser("report")
    r.add_argument("raw", type=Path, nargs="+")
    r.add_argument("--gate", default="", help="GateConfig fields as JSON, e.g. '{\"min_score\": 0.1}'.")
    r.add_argument("--verbose", action="store_true")
    a = ap.parse_args()
    collect(a) if a.cmd == "collect" else report(a)


if __name__ == "__main__":
    main()
