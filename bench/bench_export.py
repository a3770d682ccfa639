"""FP32 torch, FP32 ONNX and INT8 ONNX side by side from one run, and the edge latency breakdown.

Part 1 (accuracy + ms): a map -> bundle -> the same test split through the desktop torch path
(`acesplat eval`'s evaluate) and through the edge runtime with each ONNX model. By default the
map is fitted to the analytic test room in a minute (tests/test_edge_scene.py); pass --map and
--scene to use a real map (e.g. one made with the pretrained encoder on the built-in scene).

Part 2 (latency at the default input size): the edge encoder architecture (EDGE_ENCODER, head
width 256) exported at --size (default 360x480) with random weights, calibrated and profiled on
rendered frames. Random weights give the real inference cost but not real correspondences, so the
PnP target is measured on 2700 synthetic correspondences with 40% outliers (bench/pnp_choice.py
does the same) and the end-to-end estimate adds that to the measured capture+preprocess+inference.

Usage: python bench/bench_export.py [--map MAP --scene SCENE] [--size 360x480] [--frames 30] [--threads N]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from acesplat.core.bundle import load_bundle  # noqa: E402
from acesplat.core.metrics import timing_stats  # noqa: E402
from acesplat.core.pnp import solve_pnp  # noqa: E402
from edge.inference import default_threads  # noqa: E402
from edge.profile import cpu_model, profile_precision  # noqa: E402
from edge.replay import replay_split  # noqa: E402
from edge.runtime import STAGES, EdgeLocalizer  # noqa: E402

KEYS = (
    "localized",
    "median_translation_m",
    "median_rotation_deg",
    "recall_5cm_5deg",
    "recall_10cm_5deg",
    "recall_25cm_2deg",
    "mean_ms",
)


def accuracy_part(map_path: Path | None, scene: Path | None, threads: int, work: Path) -> None:
    from acesplat.core.scene import read_split
    from acesplat.scr.localize import Localizer, evaluate
    from acesplat.scr.mapfile import encoder_for_map, load_map
    from export.bundle_export import ExportOptions, export_bundle

    if map_path is None:
        from tests.test_edge_scene import make_room_scene, train_tiny_map

        # The fitted map memorises its views (it does not generalise to new ones), so the test views repeat
        # training views: what is compared here is how much each runtime loses from one map, not the map.
        scene = make_room_scene(work / "room", train=24, test=8, size=(96, 128), test_offset_m=0.0, test_offset_deg=0.0)
        t0 = time.time()
        map_path, _ = train_tiny_map(scene, work)
        print(f"fitted the analytic-room map in {time.time() - t0:.0f} s (96x128; 8 test views = training views)")
    t0 = time.time()
    rep = export_bundle(map_path, work / "bundle", ExportOptions(int8=True, scene_path=scene))
    par = rep.manifest["checks"]["fp32_vs_torch"]
    print(
        f"export with INT8 + self-checks: {time.time() - t0:.0f} s; FP32 ONNX vs torch on the same input: max |diff| "
        f"fraction {par['max_abs_diff_fraction']:.2e}, poses of {par['pose_frames_compared']} frames differ by at most "
        f"{1000 * par['pose_max_translation_diff_m']:.3f} mm / {par['pose_max_rotation_diff_deg']:.4f} deg "
        "(target 1 mm / 0.01 deg)"
    )
    m = load_map(map_path)
    torch.set_num_threads(threads)
    net = m.network(encoder_for_map(m, map_path))
    b = load_bundle(work / "bundle")
    # torch at the bundle's exact (stride-aligned) size, so the rows differ only by runtime and precision
    rows = {"FP32 torch": evaluate(read_split(scene, "test"), Localizer(net, min(b.input_size), {}, b.input_size))}
    for p in ("fp32", "int8"):
        rows[f"{p.upper()} ONNX"] = replay_split(EdgeLocalizer(b, p, threads), scene, "test")
    print(f"\naccuracy on {scene} / test ({b.input_size[0]}x{b.input_size[1]})")
    print(f"{'':12s}" + "".join(f"{k:>22s}" for k in KEYS))
    for name, s in rows.items():
        print(
            f"{name:12s}"
            + "".join(
                f"{'-' if s[k] is None else (f'{s[k]:.4g}' if isinstance(s[k], float) else str(s[k])):>22s}"
                for k in KEYS
            )
        )
    for p in ("FP32 ONNX", "INT8 ONNX"):
        t = rows[p]["timing_ms"]
        print(f"{p} stage p50 ms: " + ", ".join(f"{s} {t[s]['p50']:.2f}" for s in STAGES))
    quant_variants(work, scene, b.input_size, threads)


def quant_variants(work: Path, scene: Path, size: tuple[int, int], threads: int) -> None:
    """Why the shipped INT8 scheme: coordinate deviation from FP32 and localization for a few alternatives."""

    from acesplat.core.bundle import ROLE_SCR_FP32, ROLE_SCR_INT8, describe_file, write_manifest
    from acesplat.core.scene import read_split
    from edge.inference import ScrSession
    from export.checks import prepare_frames
    from export.quantize import quantize_int8

    fp32 = work / "bundle" / "scr.onnx"
    calib = [c.gray for c in prepare_frames(read_split(scene, "train").frames, size)]
    test = prepare_frames(read_split(scene, "test").frames, size)
    ref_sess = ScrSession(fp32, size, threads)
    refs = [ref_sess.run(f.gray) for f in test]
    variants = {
        "MinMax, last conv + tail float": dict(method="minmax", float_tail=True, float_convs=1),
        "MinMax, every conv INT8 (tail float)": dict(method="minmax", float_tail=False),
        "Percentile, last conv + tail float": dict(method="percentile", float_tail=True, float_convs=1),
        "MinMax, head's fc1-fc3 float": dict(method="minmax", float_tail=True, float_convs=3),
        "MinMax, res block + fc1-fc3 float (6, shipped)": dict(method="minmax", float_tail=True, float_convs=6),
        "MinMax, head float but res3_conv1 (8)": dict(method="minmax", float_tail=True, float_convs=8),
        "MinMax, whole head float (10 convs)": dict(method="minmax", float_tail=True, float_convs=10),
    }
    print(
        "\nINT8 variants on the same map (coordinate deviation from FP32 ONNX over test cells; replay of the test "
        "split)"
    )
    for name, kw in variants.items():
        root = work / f"q_{abs(hash(name))}"
        root.mkdir()
        import shutil

        shutil.copy(fp32, root / "scr.onnx")
        t0 = time.time()
        quantize_int8(root / "scr.onnx", root / "scr.int8.onnx", calib, **kw)
        qs = time.time() - t0
        write_manifest(
            root,
            {"scr": {"input_size": list(size), "output_stride": 8}},
            [describe_file(root, "scr.onnx", ROLE_SCR_FP32), describe_file(root, "scr.int8.onnx", ROLE_SCR_INT8)],
        )
        sess = ScrSession(root / "scr.int8.onnx", size, threads)
        dev = np.concatenate([np.linalg.norm(sess.run(f.gray) - r, axis=-1).ravel() for f, r in zip(test, refs)])
        s = replay_split(EdgeLocalizer(load_bundle(root), "int8", threads), scene, "test")
        print(
            f"  {name:50s} deviation median {100 * np.median(dev):6.2f} cm, p90 "
            f"{100 * np.percentile(dev, 90):6.2f} cm; localized {s['localized']}/{s['frames']}, "
            f"5cm/5deg {s['recall_5cm_5deg']:.1f}%, 10cm/5deg "
            f"{s['recall_10cm_5deg']:.1f}%, median {_num(s['median_translation_m'])} m / "
            f"{_num(s['median_rotation_deg'])} deg, "
            f"inference p50 {s['timing_ms']['inference']['p50']:.2f} ms; quantized in {qs:.0f} s"
        )


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def synthetic_pnp_ms(n: int = 20) -> dict:
    from acesplat.core.camera import Intrinsics
    from acesplat.core.geometry import look_at, transform_points
    from acesplat.core.grid import cell_centers
    from edge.runtime import PnPSettings

    rng = np.random.default_rng(0)
    intr = Intrinsics(430.0, 430.0, 239.5, 179.5, 480, 360)
    ms = []
    for _ in range(n):
        T = look_at(np.array([0.3, -0.2, 1.5]) + rng.normal(0, 0.3, 3), np.array([0.5, 4.0, 1.2]))
        pix = cell_centers(45, 60)
        X = transform_points(
            T, intr.unproject(pix + rng.normal(0, 1.0, pix.shape), 3.0 + rng.uniform(0, 2.0, len(pix)))
        )
        bad = rng.random(len(X)) < 0.4
        X[bad] += rng.normal(0, 2.0, (bad.sum(), 3))
        t0 = time.perf_counter()
        solve_pnp(pix, X, intr, **PnPSettings().kwargs())
        ms.append((time.perf_counter() - t0) * 1000)
    return timing_stats(ms[2:])


def latency_part(size: tuple[int, int], frames: int, threads: int, work: Path) -> None:
    from acesplat.core.bundle import ROLE_SCR_FP32, ROLE_SCR_INT8, describe_file, write_manifest
    from acesplat.core.camera import Intrinsics
    from acesplat.scr.network import Encoder, Head, HeadConfig, SCRNetwork
    from acesplat.scr.pretrain import EDGE_ENCODER
    from export.onnx_graph import export_scr_onnx
    from export.quantize import quantize_int8
    from tests.test_edge_scene import _texture, camera_poses, render

    h, w = size
    torch.manual_seed(0)
    net = SCRNetwork(
        Encoder(EDGE_ENCODER), Head(torch.tensor([2.0, 1.5, 1.2]), EDGE_ENCODER.out, HeadConfig(width=256))
    ).eval()
    root = work / "latency_bundle"
    root.mkdir()
    rng = np.random.default_rng(1)
    textures = [_texture(rng) for _ in range(6)]
    intr = Intrinsics.from_focal(0.9 * w, w, h)
    views = [render(textures, T, intr)[0] for T in camera_poses(frames + 5, 0.1, rng)]
    t0 = time.time()
    export_scr_onnx(net, size, root / "scr.onnx")
    import cv2

    quantize_int8(root / "scr.onnx", root / "scr.int8.onnx", [cv2.cvtColor(v, cv2.COLOR_RGB2GRAY) for v in views[:8]])
    print(
        f"\nlatency model: EDGE_ENCODER {EDGE_ENCODER.as_dict()}, head 256, random weights, exported + quantized in "
        f"{time.time() - t0:.0f} s"
    )
    write_manifest(
        root,
        {"scr": {"input_size": [h, w], "output_stride": 8}},
        [describe_file(root, "scr.onnx", ROLE_SCR_FP32), describe_file(root, "scr.int8.onnx", ROLE_SCR_INT8)],
    )
    b = load_bundle(root)
    frames_dir = work / "latency_frames"
    frames_dir.mkdir()
    for i, v in enumerate(views):
        cv2.imwrite(str(frames_dir / f"{i:04d}.png"), cv2.cvtColor(v, cv2.COLOR_RGB2BGR))
    (frames_dir / "intrinsics.json").write_text(f'{{"K": {intr.K.tolist()}, "width": {w}, "height": {h}}}')
    from edge.profile import read_frames
    from edge.sources import ReplaySource

    data = read_frames(ReplaySource(frames_dir), len(views))  # capture = PNG read + decode, as a replay does
    runs = {p: profile_precision(EdgeLocalizer(b, p, threads), data, 5) for p in ("fp32", "int8")}
    pnp = synthetic_pnp_ms()
    print(f"per-stage ms at {h}x{w}, {threads} threads, {frames} frames after 5 warm-up (mean / p50 / p95 / max):")
    for p, r in runs.items():
        print(
            f"  {p}: "
            + "; ".join(
                f"{s} {r['stages'][s]['mean']:.1f}/{r['stages'][s]['p50']:.1f}/"
                f"{r['stages'][s]['p95']:.1f}/{r['stages'][s]['max']:.1f}"
                for s in STAGES
            )
        )
    print(
        f"  PnP on 2700 realistic correspondences (40% outliers): p50 {pnp['p50']:.1f} ms, p95 {pnp['p95']:.1f} ms, "
        f"max {pnp['max']:.1f} ms"
    )
    for p, r in runs.items():
        st = r["stages"]
        e50 = st["capture"]["p50"] + st["preprocess"]["p50"] + st["inference"]["p50"] + pnp["p50"]
        e95 = st["capture"]["p95"] + st["preprocess"]["p95"] + st["inference"]["p95"] + pnp["p95"]
        print(
            f"  {p} end-to-end estimate: p50 {e50:.1f} ms, p95 {e95:.1f} ms (targets INT8: p50 <= 60, p95 <= 90; PnP "
            "<= 15)"
        )
    print(
        "  INT8 inference speed-up (p50): "
        f"{runs['fp32']['stages']['inference']['p50'] / runs['int8']['stages']['inference']['p50']:.2f}x"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--map", type=Path)
    ap.add_argument("--scene", type=Path)
    ap.add_argument("--size", default="360x480")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--threads", type=int, default=default_threads())
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--skip-latency", action="store_true")
    args = ap.parse_args()
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; threads {args.threads}; load average {os.getloadavg()}")
    work = Path(tempfile.mkdtemp(prefix="bench_export_"))
    if not args.skip_accuracy:
        accuracy_part(args.map, args.scene, args.threads, work)
    if not args.skip_latency:
        latency_part(tuple(int(v) for v in args.size.split("x")), args.frames, args.threads, work)
    print(f"\nload average after: {os.getloadavg()} (other jobs on the machine inflate every number above)")


if __name__ == "__main__":
    main()
