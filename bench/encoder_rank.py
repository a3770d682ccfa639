"""What a low-rank encoder (`acesplat export --encoder-rank R`) costs and buys, per rank, on one map: the share of
variance the fit keeps on the training images, the test cells' reprojection accuracy under the true pose (torch FP32
and the U8U8 INT8 graph), the stride-8 pose and each graph's inference time, the graphs timed interleaved.

    PYTHONPATH=. python -P bench/encoder_rank.py MAP SCENE [--ranks 0,96,128,192] [--runs 15] [--json OUT]

Rank 0 is the exact encoder. The fit uses the export's calibration frames (training split), never the test views.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from acesplat.core.atomic import write_json
from acesplat.core.geometry import pose_error
from acesplat.core.grid import cell_reprojection_errors
from acesplat.core.machine import cpu_isa, machine_line
from acesplat.core.pnp import solve_from_grid
from acesplat.core.scene import read_split
from acesplat.scr.lowrank import lowrank_encoder
from acesplat.scr.mapfile import encoder_for_map, load_map
from acesplat.scr.network import SCRNetwork
from edge.inference import session_options
from export.bundle_export import default_size, evenly
from export.checks import onnx_coords, prepare_frames, torch_coords
from export.onnx_graph import export_scr_onnx
from export.options import ExportOptions
from export.quantize import quantize_int8

PX = (1.0, 4.0)


def score(predict, frames) -> dict:
    """Test cells within PX of their pixel under the true pose, and the pose's translation error per frame."""
    within, pose_cm, good = [], [], []
    for f in frames:
        c = predict(f.gray)
        err = cell_reprojection_errors(c, f.pose, f.intrinsics.K)
        within.append([float(np.mean(err < t)) for t in PX])
        res = solve_from_grid(c, f.intrinsics)
        t, r = pose_error(res.T_c2w, f.pose) if res.T_c2w is not None else (float("inf"), float("inf"))
        pose_cm.append(100.0 * t)
        good.append(t <= 0.05 and r <= 5.0)
    return {
        "within_5cm_5deg": float(np.mean(good)),
        "cells_within_px": dict(zip([f"{t:g}" for t in PX], np.mean(within, axis=0).tolist())),
        "pose_median_cm": float(np.median(pose_cm)),
        "pose_cm": pose_cm,
    }


def _cells(sc: dict) -> str:
    c = sc["cells_within_px"]
    return f"{c['1']:.3f} / {c['4']:.3f}, {sc['pose_median_cm']:.2f} cm, {100 * sc['within_5cm_5deg']:.1f}%"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("map", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--ranks", default="0,96,128,192")
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(2)
    m = load_map(args.map)
    net = m.network(encoder_for_map(m, args.map))
    size = default_size(args.scene, m.short_side, args.map)
    opts = ExportOptions()
    fit = prepare_frames(evenly(read_split(args.scene, "train").frames, opts.calibration_frames), size)
    test = prepare_frames(read_split(args.scene, "test").frames, size)
    work = Path(tempfile.mkdtemp(prefix="encoder_rank."))
    rows, sessions = [], {}
    for rank in [int(r) for r in args.ranks.split(",")]:
        row: dict = {"rank": rank}
        n = net
        if rank:
            enc, rep = lowrank_encoder(net.encoder, [f.gray for f in fit], rank)
            n = SCRNetwork(enc, net.head).eval()
            row.update(kept_variance=rep["kept_variance"], macs_ratio=rep["macs_per_cell"] / rep["macs_per_cell_full"])
        fp32, int8 = work / f"r{rank}.onnx", work / f"r{rank}.int8.onnx"
        export_scr_onnx(n, size, fp32)
        quantize_int8(
            fp32, int8, [f.gray for f in fit], quant_format=opts.int8_format, types=opts.int8_types, per_channel=True
        )
        row["torch_fp32"] = score(lambda g, n=n: torch_coords(n, g), test)
        for label, path in (("fp32", fp32), ("u8u8", int8)):
            s = ort.InferenceSession(str(path), sess_options=session_options(), providers=["CPUExecutionProvider"])
            sessions[(rank, label)] = s
            if label == "u8u8":
                row["onnx_u8u8"] = score(lambda g, s=s: onnx_coords(s, g), test)
        rows.append(row)
    gray = test[0].gray.astype(np.float32)[None, None]
    times: dict = {k: [] for k in sessions}
    for s in sessions.values():
        s.run(None, {s.get_inputs()[0].name: gray})
    for _ in range(args.runs):  # interleaved: a changing load hits every graph alike
        for k, s in sessions.items():
            t0 = time.perf_counter()
            s.run(None, {s.get_inputs()[0].name: gray})
            times[k].append(1000.0 * (time.perf_counter() - t0))
    print(machine_line())
    print(f"{args.map} on {args.scene} at {size[0]}x{size[1]}, onnxruntime {ort.__version__}")
    print("rank | kept var | layer MACs | FP32 ms | U8U8 ms | torch FP32: <1 / <4 px, pose median, 5 cm/5 deg | U8U8")
    for row in rows:
        r = row["rank"]
        row["ms"] = {lab: float(np.median(times[(r, lab)])) for lab in ("fp32", "u8u8")}
        print(
            f"{r or 'exact':>5} | {row.get('kept_variance', 1.0):.4f} | {row.get('macs_ratio', 1.0):.2f} | "
            f"{row['ms']['fp32']:.1f} | {row['ms']['u8u8']:.1f} | "
            f"{_cells(row['torch_fp32'])} | {_cells(row['onnx_u8u8'])}"
        )
    if args.json:
        write_json(args.json, {"machine": machine_line(), "cpu_isa": cpu_isa(), "size": list(size), "rows": rows})


if __name__ == "__main__":
    main()
