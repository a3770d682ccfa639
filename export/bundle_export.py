"""Map -> bundle: export the SCR graph (and its INT8 twin), check both, write the manifest, swap into place.

The bundle is assembled in a temporary sibling directory and renamed into place at the end, so an
interrupted export never leaves a half-written bundle where a good one was.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from onnxruntime import __version__ as ort_version

from acesplat import __version__
from acesplat.align.keyframe_set import save_keyframes
from acesplat.core.bundle import (
    MANIFEST_NAME,
    ROLE_INT8_CHECK,
    ROLE_KEYFRAMES,
    ROLE_SCR_FP32,
    ROLE_SCR_INT8,
    ROLE_SCR_INT8_VNNI,
    BundleFile,
    describe_file,
    sha256_of,
    write_manifest,
)
from acesplat.core.camera import Intrinsics
from acesplat.core.check_frames import CheckFrames, deviation, save_check_frames
from acesplat.core.errors import InputError
from acesplat.core.grid import DENSE_OUTPUT_STRIDE, OUTPUT_STRIDE
from acesplat.core.machine import cpu_isa
from acesplat.core.preprocess import size_for_short_side
from acesplat.core.scene import IMAGE_SUFFIXES, SceneSplit, image_size, read_split
from acesplat.scr.lowrank import lowrank_encoder
from acesplat.scr.mapfile import encoder_for_map, load_map
from acesplat.scr.network import GRAY_MEAN, GRAY_STD, SCRNetwork
from export.checks import (
    CheckFrame,
    fp32_parity,
    localization_accuracy,
    onnx_coords,
    onnx_session,
    prepare_frames,
    torch_coords,
)
from export.onnx_graph import FEATURES_NAME, INPUT_NAME, OPSET, OUTPUT_NAME, export_scr_onnx
from export.options import ExportOptions, check_int8_options, int8_scheme_text, vnni_options
from export.quantize import quantize_int8

FP32_FILE = "scr.onnx"
KEYFRAMES_FILE = "keyframes.npz"
INT8_FILE = "scr.int8.onnx"
INT8_VNNI_FILE = "scr.int8.u8s8.onnx"
CHECK_FILE = "int8_check.npz"
PARITY_FRAMES = 8
"""Frames the FP32 graph is compared with torch on."""

ProgressFn = Callable[[str, float, dict], None]


@dataclass
class ExportReport:
    bundle: Path
    manifest: dict
    seconds: float
    timings: dict = field(default_factory=dict)


def round_to_stride(n: int, stride: int = OUTPUT_STRIDE) -> int:
    return max(stride, int(round(n / stride)) * stride)


def default_size(scene: Path | None, short_side: int, map_path: Path) -> tuple[int, int]:
    """The map's short side with the training images' aspect ratio, each side a multiple of the output stride."""
    if scene is None or not (scene / "train" / "rgb").is_dir():
        raise InputError(
            map_path, f"cannot choose the input size: scene folder {scene} not found; pass --size HxW or --scene"
        )
    images = sorted(p for p in (scene / "train" / "rgb").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise InputError(scene / "train" / "rgb", "no training images to take the aspect ratio from")
    w, h = image_size(images[0])
    sh, sw = size_for_short_side(h, w, short_side)
    return round_to_stride(sh), round_to_stride(sw)


def evenly(items: list, n: int) -> list:
    if n <= 0 or len(items) <= n:
        return list(items)
    idx = np.linspace(0, len(items) - 1, n).round().astype(int)
    return [items[i] for i in idx]


def _try_split(scene: Path | None, split: str) -> SceneSplit | None:
    if scene is None or not (scene / split).is_dir():
        return None
    return read_split(scene, split)


def _prepare_out(out: Path) -> None:
    if out.exists():
        if not out.is_dir():
            raise InputError(out, "output exists and is not a directory")
        if any(out.iterdir()) and not (out / MANIFEST_NAME).is_file():
            raise InputError(out, "output directory is not empty and not a bundle; refusing to replace it")


def _swap_into_place(tmp: Path, out: Path) -> None:
    """Rename the finished bundle over ``out``; the old bundle is removed only after the new one is in place."""
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _write_check_frames(tmp: Path, frames: list, size: tuple[int, int], stride: int, vnni: bool) -> dict:
    """Store ``frames`` prepared at ``size`` with their FP32 and INT8 coordinates (and, with ``vnni``, the U8S8
    twin's) in the bundle written at ``tmp``; the INT8-vs-FP32 deviation on this machine by INT8 precision (what
    `acesplat-edge check` compares the device with)."""
    prepared = prepare_frames(frames, size)
    fp32, int8 = onnx_session(tmp / FP32_FILE), onnx_session(tmp / INT8_FILE)
    ref = [onnx_coords(fp32, f.gray).astype(np.float32) for f in prepared]
    q = [onnx_coords(int8, f.gray).astype(np.float32) for f in prepared]
    qv = None
    if vnni:
        sess = onnx_session(tmp / INT8_VNNI_FILE)
        qv = [onnx_coords(sess, f.gray).astype(np.float32) for f in prepared]
    intr = [f.intrinsics for f in prepared]
    save_check_frames(
        tmp / CHECK_FILE,
        CheckFrames(
            [f.name for f in prepared],
            np.stack([f.gray for f in prepared]),
            np.stack([i.K for i in intr]),
            np.stack(ref),
            np.stack(q),
            stride,
            None if qv is None else np.stack(qv),
        ),
    )
    machine = {"units": "scene units (metres) and degrees", "cpu_isa": cpu_isa(), "onnxruntime": ort_version}
    out = {"int8": {**deviation(ref, q, intr, stride), **machine}}
    if qv is not None:
        out["int8_vnni"] = {**deviation(ref, qv, intr, stride), **machine}
    return out


def _quantize(tmp: Path, name: str, calib: list, opts: ExportOptions) -> None:
    """The FP32 graph at ``tmp`` quantized into ``tmp / name`` with ``opts``' INT8 scheme, calibrated on ``calib``."""
    quantize_int8(
        tmp / FP32_FILE,
        tmp / name,
        [c.gray for c in calib],
        quant_format=opts.int8_format,
        types=opts.int8_types,
        per_channel=opts.int8_per_channel,
        reduce_range=opts.int8_reduce_range,
        method=opts.int8_calibration,
        percentile=opts.int8_percentile,
    )


def export_bundle(map_path: Path, out: Path, opts: ExportOptions, progress: ProgressFn | None = None) -> ExportReport:
    """Export ``map_path`` to the bundle directory ``out``; returns the manifest written."""
    t_start = time.monotonic()
    map_path, out = Path(map_path), Path(out)
    _prepare_out(out)
    check_int8_options(opts)
    m = load_map(map_path)
    enc = encoder_for_map(m, map_path, opts.encoder_path)
    net = m.network(enc)
    scene = opts.scene_path or (Path(m.metadata["scene"]) if m.metadata.get("scene") else None)
    if opts.size_hw is not None:
        h, w = opts.size_hw
        if h % OUTPUT_STRIDE or w % OUTPUT_STRIDE:
            raise InputError(None, f"--size must be a multiple of {OUTPUT_STRIDE} in both sides, got {h}x{w}")
        size = (h, w)
    else:
        size = default_size(scene, m.short_side, map_path)
    stride = DENSE_OUTPUT_STRIDE if opts.dense else OUTPUT_STRIDE
    train = _try_split(scene, "train")
    test = _try_split(scene, "test")
    if opts.int8 and train is None:
        raise InputError(
            map_path, f"--int8 calibrates on the map's training images, but {scene}/train was not found; pass --scene"
        )
    if opts.keyframes and train is None:
        raise InputError(
            map_path, f"--keyframes takes the map's training images, but {scene}/train was not found; pass --scene"
        )
    if opts.encoder_rank:
        if train is None:
            raise InputError(
                map_path,
                f"--encoder-rank fits on the map's training images, but {scene}/train was not found; pass --scene",
            )
        if enc.cfg.rank:
            raise InputError(
                map_path, f"--encoder-rank: the map's encoder is already factorized (rank {enc.cfg.rank}); pass 0"
            )
        if enc.cfg.separable:
            raise InputError(map_path, "--encoder-rank: the map's encoder's last layer is separable; pass 0")
        if not 0 < opts.encoder_rank < enc.cfg.out:
            raise InputError(
                None,
                f"--encoder-rank must be between 1 and {enc.cfg.out - 1} for this encoder "
                f"(0 keeps it exact), got {opts.encoder_rank}",
            )
    timings: dict[str, float] = {}
    checks: dict = {}
    vnni = vnni_options(opts)
    exact_net = net
    lowrank: dict | None = None
    calib: list[CheckFrame] = []  # the training images that fit a low-rank encoder and calibrate INT8, read once

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o777 & ~mask)  # mkdtemp makes 0700; a bundle is meant to be copied and shared
    try:
        if opts.encoder_rank:
            t0 = time.monotonic()
            if progress:
                progress("fit encoder rank", 0.0, {})
            calib = prepare_frames(evenly(train.frames, opts.calibration_frames), size)
            enc_lr, lowrank = lowrank_encoder(net.encoder, [f.gray for f in calib], opts.encoder_rank)
            net = SCRNetwork(enc_lr, net.head).eval()
            timings["encoder_rank_s"] = time.monotonic() - t0
            if progress:
                progress("fit encoder rank", 1.0, {})
        t0 = time.monotonic()
        if progress:
            progress("export fp32", 0.0, {})
        export_scr_onnx(net, size, tmp / FP32_FILE, stride)
        timings["export_fp32_s"] = time.monotonic() - t0
        if progress:
            progress("export fp32", 1.0, {})
        files: list[BundleFile] = [describe_file(tmp, FP32_FILE, ROLE_SCR_FP32)]

        parity_src = test or train
        if parity_src is not None:
            parity_frames = prepare_frames(evenly(parity_src.frames, PARITY_FRAMES), size)
            checks["fp32_vs_torch"] = fp32_parity(net, tmp / FP32_FILE, parity_frames, progress, stride)
            if lowrank is not None:
                # what the low-rank encoder costs against the exact one, in torch, measured as INT8 against FP32
                exact = [torch_coords(exact_net, f.gray, stride) for f in parity_frames]
                cheap = [torch_coords(net, f.gray, stride) for f in parity_frames]
                lowrank.update(deviation(exact, cheap, [f.intrinsics for f in parity_frames], stride))
        else:
            rng = np.random.default_rng(0)
            noise = [
                CheckFrame(
                    f"noise{i}",
                    rng.integers(0, 256, size, dtype=np.uint8),
                    Intrinsics.from_focal(max(size), size[1], size[0]),
                    np.eye(4),
                )
                for i in range(2)
            ]
            checks["fp32_vs_torch"] = fp32_parity(net, tmp / FP32_FILE, noise, progress, stride)
            checks["fp32_vs_torch"]["note"] = "scene not found: compared on random images"

        if opts.int8:
            t0 = time.monotonic()
            calib = calib or prepare_frames(evenly(train.frames, opts.calibration_frames), size)
            if progress:
                progress("quantize int8", 0.0, {"images": len(calib)})
            _quantize(tmp, INT8_FILE, calib, opts)
            timings["quantize_int8_s"] = time.monotonic() - t0
            if progress:
                progress("quantize int8", 1.0, {"images": len(calib)})
            files.append(describe_file(tmp, INT8_FILE, ROLE_SCR_INT8))
            if vnni is not None:
                t0 = time.monotonic()
                _quantize(tmp, INT8_VNNI_FILE, calib, vnni)
                timings["quantize_int8_vnni_s"] = time.monotonic() - t0
                files.append(describe_file(tmp, INT8_VNNI_FILE, ROLE_SCR_INT8_VNNI))
            checks["int8_calibration_frames"] = len(calib)
            if opts.check_frames > 0:
                t0 = time.monotonic()
                by_precision = _write_check_frames(
                    tmp, evenly((test or train).frames, opts.check_frames), size, stride, vnni is not None
                )
                checks["int8_vs_fp32"] = by_precision["int8"]
                if "int8_vnni" in by_precision:
                    checks["int8_vnni_vs_fp32"] = by_precision["int8_vnni"]
                files.append(describe_file(tmp, CHECK_FILE, ROLE_INT8_CHECK))
                timings["check_frames_s"] = time.monotonic() - t0
            if test is not None:
                t0 = time.monotonic()
                test_frames = prepare_frames(test.frames, size)
                acc = {
                    "fp32": localization_accuracy(tmp / FP32_FILE, test_frames, "fp32", progress, stride),
                    "int8": localization_accuracy(tmp / INT8_FILE, test_frames, "int8", progress, stride),
                }
                if vnni is not None:
                    acc["int8_vnni"] = localization_accuracy(
                        tmp / INT8_VNNI_FILE, test_frames, "int8_vnni", progress, stride
                    )
                acc["recall_drop_points"] = {
                    k: acc["fp32"][k] - acc["int8"][k]
                    for k in ("recall_5cm_5deg", "recall_10cm_5deg", "recall_25cm_2deg")
                }
                checks["test_split"] = acc
                timings["check_int8_s"] = time.monotonic() - t0
            else:
                checks["test_split"] = None
                checks["test_split_note"] = "scene has no test split: INT8 accuracy not checked"

        keyframes_info = None
        if opts.keyframes:
            t0 = time.monotonic()
            if progress:
                progress("keyframes", 0.0, {"images": len(train.frames)})
            from acesplat.scr.keyframes import MapKeyframes

            ks = MapKeyframes(train, exact_net, m.short_side, input_size=size).to_set()
            save_keyframes(tmp / KEYFRAMES_FILE, ks)
            files.append(describe_file(tmp, KEYFRAMES_FILE, ROLE_KEYFRAMES))
            keyframes_info = {
                "count": len(ks),
                "image_size": list(ks.gray.shape[1:]),
                "depth_stride": ks.stride,
                "depth_from": "the map's head (dense grid, median-filtered), re-measured between keyframes",
            }
            timings["keyframes_s"] = time.monotonic() - t0
            if progress:
                progress("keyframes", 1.0, {"images": len(ks)})

        manifest = {
            "created_by": f"acesplat-edge {__version__}",
            "created_unix": time.time(),
            "scene": {"name": scene.name if scene else map_path.stem, "path": str(scene.resolve()) if scene else None},
            "source_map": {"path": str(map_path.resolve()), "sha256": sha256_of(map_path)},
            "scr": {
                "input_size": [size[0], size[1]],
                "dynamic_size": True,
                "output_stride": stride,
                "output_size": [size[0] // stride, size[1] // stride],
                "input": {
                    "name": INPUT_NAME,
                    "shape": [1, 1, size[0], size[1]],
                    "dtype": "float32",
                    "content": "grayscale intensities in [0, 255] (uint8 values as float)",
                },
                "output": {
                    "name": OUTPUT_NAME,
                    "shape": [1, 3, size[0] // stride, size[1] // stride],
                    "content": "scene coordinates (x, y, z) in scene units per cell; "
                    f"cell (i, j) is pixel ({stride}j+4, {stride}i+4)",
                },
                "features": {
                    "name": FEATURES_NAME,
                    "shape": [1, net.encoder.cfg.out, size[0] // stride, size[1] // stride],
                    "content": "the encoder's features per cell (the head's input; the splat initializer's input)",
                },
                "normalization": {
                    "formula": "(x / 255 - mean) / std",
                    "mean": GRAY_MEAN,
                    "std": GRAY_STD,
                    "inside_graph": True,
                },
                "mean_offset": [float(v) for v in np.asarray(m.mean).reshape(3)],
                "encoder": {"name": m.encoder_identity.name, "sha256": m.encoder_identity.sha256},
                "encoder_lowrank": lowrank,
                "head": m.head.cfg.as_dict(),
                "opset": OPSET,
                "precisions": ["fp32"] + (["int8"] if opts.int8 else []) + (["int8_vnni"] if vnni else []),
                "int8_scheme": int8_scheme_text(opts) if opts.int8 else None,
                "int8_vnni_scheme": int8_scheme_text(vnni) if vnni else None,
            },
            "checks": checks,
        }
        if keyframes_info:
            manifest["keyframes"] = keyframes_info
        written = write_manifest(tmp, manifest, files)
        _swap_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ExportReport(bundle=out, manifest=written, seconds=time.monotonic() - t_start, timings=timings)
