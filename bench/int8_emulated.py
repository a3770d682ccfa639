"""The on-device INT8 check as a CPU without VNNI would run it, reproduced on this one by emulation.

onnxruntime picks its integer kernels by CPUID, and no environment variable hides VNNI or AVX-512 from it. qemu's
user-mode emulator (`apt-get install qemu-user`) can: under `qemu-x86_64 -cpu Haswell-v4` the same Python and
onnxruntime see an AVX2 CPU and run the AVX2 kernels, whose U8S8 products saturate (vpmaddubsw) where VNNI's are
exact. Emulation is about 1000x slower, so only numbers come out of it, never times:

1. the edge's U8S8 probe (edge.int8_check.u8s8_probe_error: a U8 x S8 product whose 16-bit pair sums overflow,
   against the same product in U8 x U8) shows which kernel ran: exact with VNNI, off by about 40% under the
   emulated AVX2 CPU;
2. the bundle's check frames run through each INT8 graph natively and emulated;
3. both are judged as `acesplat-edge check` judges a device (edge.int8_check.judge_graphs, with and without the
   probe's verdict, to show what each criterion catches), against FP32
   coordinates computed natively (FP32 kernels differ by ISA in rounding only: the row `fp32` measures that when
   `--emulate-fp32` runs it emulated too, at about 90 s a 240x320 frame).

    python -P bench/int8_emulated.py BUNDLE [--frames 4] [--cpu Haswell-v4] [--emulate-fp32] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def run_graphs(models: dict[str, str], gray: np.ndarray, input_size: tuple[int, int], threads: int) -> dict:
    """Coordinates (N, h, w, 3) of each model over the prepared inputs ``gray`` (N, H, W) uint8."""
    from edge.inference import ScrSession

    out = {}
    for name, path in models.items():
        sess = ScrSession(path, input_size, threads)
        out[name] = np.stack([sess.run(g) for g in gray])
    return out


def child(args: argparse.Namespace) -> None:
    """Runs under the emulator: the probe, then the models on the stored inputs, into one .npz."""
    with np.load(args.child, allow_pickle=False) as z:
        gray, size = z["gray"], tuple(int(v) for v in z["input_size"])
        models = dict(zip(z["names"].tolist(), z["paths"].tolist(), strict=True))
    from edge.int8_check import u8s8_probe_error

    t0 = time.perf_counter()
    result = {"probe": np.array(u8s8_probe_error())}
    result.update(run_graphs(models, gray, size, args.threads))
    result["seconds"] = np.array(time.perf_counter() - t0)
    np.savez(args.out, **result)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle", type=Path, nargs="?")
    ap.add_argument("--frames", type=int, default=4, help="Check frames compared (the check's default).")
    ap.add_argument("--cpu", default="Haswell-v4", help="qemu CPU model: Haswell-v4 is AVX2 + FMA, no AVX-512.")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--emulate-fp32", action="store_true", help="Also run FP32 emulated (slow).")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        child(args)
        return
    if args.bundle is None:
        ap.error("BUNDLE is required")
    qemu = shutil.which("qemu-x86_64")
    if qemu is None:
        sys.exit("qemu-x86_64 not found: apt-get install qemu-user")

    from acesplat.core.bundle import PRECISION_ROLES, load_bundle
    from acesplat.core.check_frames import bundle_check_frames
    from acesplat.core.machine import machine_line
    from edge.int8_check import Int8CheckConfig, judge_graphs, u8s8_probe_error

    bundle = load_bundle(args.bundle)
    frames = bundle_check_frames(bundle)
    n = min(args.frames, len(frames))
    gray = frames.gray[:n]
    int8 = [p for p in ("int8", "int8_vnni") if bundle.has(PRECISION_ROLES[p])]
    models = {p: str(bundle.scr_model(p)) for p in ["fp32", *int8]}
    native = run_graphs(models, gray, bundle.input_size, args.threads)
    emulated_models = {p: models[p] for p in int8 + (["fp32"] if args.emulate_fp32 else [])}
    with tempfile.TemporaryDirectory() as td:
        inp, outp = Path(td) / "in.npz", Path(td) / "out.npz"
        np.savez(
            inp,
            gray=gray,
            input_size=np.array(bundle.input_size),
            names=np.array(list(emulated_models)),
            paths=np.array(list(emulated_models.values())),
        )
        cmd = [qemu, "-cpu", args.cpu, sys.executable, "-P", __file__, "--child", str(inp), "--out", str(outp)]
        cmd += ["--threads", str(args.threads)]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            errs = [ln for ln in proc.stderr.splitlines() if "TCG doesn't support" not in ln]
            sys.exit("emulated run failed:\n" + "\n".join(errs[-20:]))
        with np.load(outp, allow_pickle=False) as z:
            emulated = {k: z[k] for k in z.files}
    ref = list(native["fp32"])
    config = Int8CheckConfig(frames=n)
    probes = {"native": u8s8_probe_error(), "emulated": float(emulated["probe"])}
    grids = {"native": native, "emulated": emulated}
    verdicts = {
        (where, probed): judge_graphs(
            bundle, frames, ref, {p: list(grids[where][p]) for p in int8}, config, probes[where] if probed else None
        )
        for where in grids
        for probed in (False, True)
    }
    rows = []
    print(f"# {machine_line()}; emulated CPU: qemu-x86_64 -cpu {args.cpu} ({wall:.0f} s)")
    print(f"bundle {args.bundle}, {n} check frames, input {bundle.input_size[0]}x{bundle.input_size[1]}")
    print(f"U8S8 probe (relative error): native {probes['native']:.3f}, emulated {probes['emulated']:.3f}")
    if "fp32" in emulated:
        d = np.abs(emulated["fp32"].astype(np.float64) - native["fp32"]).max()
        print(f"FP32 emulated against native: max |difference| {100 * d:.4f} cm")
    print(
        "| graph | CPU | identical to native | coord median / p90 cm | pose median / max cm | "
        "rotation median / max deg | check by figures | check with the probe |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for p in int8:
        same = float(np.abs(emulated[p].astype(np.float64) - native[p]).max())
        for where in ("native", "emulated"):
            device, export, bounds, failures = verdicts[(where, False)][p]
            probed = verdicts[(where, True)][p][3]
            row = {
                "graph": p,
                "cpu": where,
                "max_abs_vs_native_m": 0.0 if where == "native" else same,
                "device": device,
                "export": export,
                "bounds": bounds,
                "failures": failures,
                "failures_with_probe": probed,
            }
            rows.append(row)
            print(
                f"| {p} | {where if where == 'native' else args.cpu} | "
                f"{'-' if where == 'native' else ('yes' if same == 0.0 else f'no, max {100 * same:.2f} cm')} | "
                f"{100 * device['coord_median']:.2f} / {100 * device['coord_p90']:.2f} | "
                f"{100 * (device['pose_median_translation'] or np.nan):.2f} / "
                f"{100 * (device['pose_max_translation'] or np.nan):.2f} | "
                f"{device['pose_median_rotation_deg'] or np.nan:.3f} / "
                f"{device['pose_max_rotation_deg'] or np.nan:.3f} | "
                f"{'passed' if not failures else 'FAILED: ' + failures[0]} | "
                f"{'passed' if not probed else 'FAILED: ' + probed[0]} |"
            )
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "machine": machine_line(),
                    "emulated_cpu": args.cpu,
                    "bundle": str(args.bundle),
                    "frames": n,
                    "probe": probes,
                    "rows": rows,
                },
                indent=1,
            )
        )


if __name__ == "__main__":
    main()
