"""Which INT8 scheme: every form/type/per-channel/reduce_range variant of onnxruntime's static quantizer, measured
against the FP32 graph on the same map: coordinate deviation (cm), PnP pose deviation (cm / deg) and inference time.

    PYTHONPATH=. python -P bench/int8_format.py MAP SCENE [--work DIR] [--threads 2] [--runs 15] [--only 3]
        [--methods minmax,percentile,percentile:99.99,entropy] [--float-convs 6,8,10] [--float-lead 0,3]

``--methods`` repeats each variant with onnxruntime's calibration methods (``percentile:P`` sets the percentile).

Writes the table to stdout and, with --json, the numbers. The decision is written up in bench/int8_format.md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

VARIANTS = [
    ("qdq", "u8s8", True, False),
    ("qdq", "u8s8", True, True),
    ("qdq", "s8s8", True, False),
    ("qdq", "u8u8", True, False),
    ("qdq", "u8s8", False, False),
    ("qdq", "s8s8", False, False),
    ("qoperator", "u8s8", True, False),
    ("qoperator", "u8s8", True, True),
    ("qoperator", "s8s8", True, False),
    ("qoperator", "u8u8", True, False),
    ("qdq", "u8u8", False, False),
    ("qdq", "u8s8", False, True),
]
"""(form, types, per_channel, reduce_range)."""


def _time_ms(sessions: dict, gray: np.ndarray, runs: int) -> dict[str, float]:
    """Median ms per session, the sessions interleaved round by round so a changing load hits them alike."""
    for s in sessions.values():
        s.run(gray)
    ts: dict[str, list[float]] = {k: [] for k in sessions}
    for _ in range(runs):
        for k, s in sessions.items():
            t0 = time.perf_counter()
            s.run(gray)
            ts[k].append((time.perf_counter() - t0) * 1000.0)
    return {k: statistics.median(v) for k, v in ts.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--work", type=Path, default=Path("/tmp/int8_format"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--calibration", type=int, default=32)
    ap.add_argument("--frames", type=int, default=16, help="Test frames compared (evenly spaced).")
    ap.add_argument("--only", nargs="*", default=None, help="Variants by index into VARIANTS (default: all).")
    ap.add_argument("--float-convs", default="6", help="Trailing convolutions kept float, comma-separated counts.")
    ap.add_argument("--float-lead", default="0", help="Leading convolutions kept float, comma-separated counts.")
    ap.add_argument("--methods", default="minmax", help="Calibration methods: minmax,percentile,entropy.")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    import onnxruntime as ort

    from acesplat.core.geometry import pose_error
    from acesplat.core.machine import cpu_isa, machine_line
    from acesplat.core.pnp import solve_from_grid
    from acesplat.core.scene import read_split
    from acesplat.scr.mapfile import encoder_for_map, load_map
    from edge.inference import ScrSession
    from export.bundle_export import default_size, evenly
    from export.checks import prepare_frames
    from export.onnx_graph import export_scr_onnx
    from export.quantize import quantize_int8

    print(machine_line())
    m = load_map(args.map)
    net = m.network(encoder_for_map(m, args.map, None))
    size = default_size(args.scene, m.short_side, args.map)
    args.work.mkdir(parents=True, exist_ok=True)
    fp32 = args.work / "scr.onnx"
    export_scr_onnx(net, size, fp32)
    train, test = read_split(args.scene, "train"), read_split(args.scene, "test")
    calib = [c.gray for c in prepare_frames(evenly(train.frames, args.calibration), size)]
    frames = prepare_frames(evenly(test.frames, args.frames), size)
    ref = ScrSession(fp32, size, args.threads)
    refs = [ref.run(f.gray) for f in frames]
    ref_poses = [solve_from_grid(c, f.intrinsics).T_c2w for c, f in zip(refs, frames, strict=True)]
    rows = [{"variant": "fp32"}]
    sessions = {"fp32": ref}
    gt = [pose_error(p, f.pose) for p, f in zip(ref_poses, frames, strict=True) if p is not None]
    rows[0]["gt_median_cm"] = 100 * float(np.median([t for t, _ in gt]))
    chosen = VARIANTS if args.only is None else [VARIANTS[int(i)] for i in args.only]
    runs = [
        (v, m, int(k), int(lead))
        for v in chosen
        for m in args.methods.split(",")
        for k in args.float_convs.split(",")
        for lead in args.float_lead.split(",")
    ]
    for (form, types, pc, rr), method, float_convs, float_lead in runs:
        name = f"{form} {types}{' per-channel' if pc else ' per-tensor'}{' reduce_range' if rr else ''}"
        name += "" if method == "minmax" else f" {method}"
        name += "" if float_convs == 6 else f" {float_convs} float convs"
        name += "" if float_lead == 0 else f" {float_lead} float leading convs"
        path = args.work / f"{form}_{types}_{int(pc)}{int(rr)}_{method}_{float_convs}_{float_lead}.onnx"
        kind, _, pct = method.partition(":")  # percentile:99.99 sets the percentile
        t0 = time.perf_counter()
        quantize_int8(
            fp32,
            path,
            calib,
            kind,
            quant_format=form,
            types=types,
            per_channel=pc,
            reduce_range=rr,
            float_convs=float_convs,
            float_lead=float_lead,
            **({"percentile": float(pct)} if pct else {}),
        )
        q_s = time.perf_counter() - t0
        sess = ScrSession(path, size, args.threads)
        dev, dt, dr, gt = [], [], [], []
        for f, r, rp in zip(frames, refs, ref_poses, strict=True):
            c = sess.run(f.gray)
            dev.append(np.linalg.norm(c - r, axis=-1).ravel())
            p = solve_from_grid(c, f.intrinsics).T_c2w
            if p is not None and rp is not None:
                t, a = pose_error(p, rp)
                dt.append(t)
                dr.append(a)
            if p is not None:
                gt.append(pose_error(p, f.pose)[0])
        d = np.concatenate(dev)
        row = {
            "variant": name,
            "coord_median_cm": 100 * float(np.median(d)),
            "coord_p90_cm": 100 * float(np.percentile(d, 90)),
            "pose_median_cm": 100 * float(np.median(dt)) if dt else None,
            "pose_max_cm": 100 * float(np.max(dt)) if dt else None,
            "pose_median_deg": float(np.median(dr)) if dr else None,
            "pose_max_deg": float(np.max(dr)) if dr else None,
            "gt_median_cm": 100 * float(np.median(gt)) if gt else None,
            "quantize_s": q_s,
        }
        rows.append(row)
        sessions[name] = sess
        print(json.dumps(row), flush=True)
    ms = _time_ms(sessions, frames[0].gray, args.runs)
    for r in rows:
        r["ms"] = ms[r["variant"]]
    header = {
        "map": str(args.map),
        "scene": str(args.scene),
        "size": list(size),
        "frames": len(frames),
        "cpu_isa": cpu_isa(),
        "onnxruntime": ort.__version__,
        "threads": args.threads,
        "machine": machine_line(),
        "command": " ".join(["python -P bench/int8_format.py", *sys.argv[1:]]),
    }
    print(json.dumps(header))
    print(
        "| format | coord median / p90 (cm) | pose median / max (cm) | pose median / max (deg) | GT median (cm) | ms |"
    )
    print("|---|---|---|---|---|---|")

    def f(v, p=2):
        return "-" if v is None else f"{v:.{p}f}"

    for r in rows:
        if r["variant"] == "fp32":
            print(f"| fp32 | - | - | - | {f(r['gt_median_cm'], 1)} | {f(r['ms'], 1)} |")
            continue
        print(
            f"| {r['variant']} | {f(r['coord_median_cm'])} / {f(r['coord_p90_cm'])} | "
            f"{f(r['pose_median_cm'])} / {f(r['pose_max_cm'])} | {f(r['pose_median_deg'], 3)} / "
            f"{f(r['pose_max_deg'], 3)} | {f(r['gt_median_cm'], 1)} | {f(r['ms'], 1)} |"
        )
    if args.json:
        args.json.write_text(json.dumps({"header": header, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
