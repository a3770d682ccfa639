"""Add a splat folder's Gaussian models to a bundle: the Gaussians (PLY) and the initializer as ONNX.

The initializer is one static-shape graph: the encoder's features (1, C, H/8, W/8), as the bundle's
SCR graph outputs them beside the coordinates, and the init head's prior (1, PRIOR_CHANNELS, H, W)
in; head residuals (1, K, H, W) out, with the feature adapter and the init head inside. The edge thus
reuses the features its localizer already computed instead of running the encoder a second time.
FP32 only: no INT8 twin is written (it would need its own quality check on rendered Gaussians); it
takes the INT8 SCR graph's dequantized features as well, and the export measures how far that moves
its output.

Files are written into the finished bundle and only then listed in its manifest (rewritten
atomically), so an interrupted run leaves the bundle as it was, plus at most an unlisted file.
The role, file and graph names are acesplat/splatcore/bundle_section.py's, which the edge reads too.
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from acesplat.core.atomic import atomic_path
from acesplat.core.bundle import SCR_FEATURES_OUTPUT, BundleFile, describe_file, load_bundle, write_manifest
from acesplat.core.errors import InputError
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.core.ply import read_ply, write_ply
from acesplat.splatcore.bundle_section import (
    GAUSSIANS_FILE,
    INIT_FILE,
    INIT_INPUTS,
    INIT_OUTPUT,
    ROLE_GAUSSIANS,
    ROLE_SPLAT_INIT,
)
from acesplat.splatcore.head_io import PRIOR_CHANNELS
from acesplat.splatcore.seeding import OPACITY_PRIOR, SCALE_PRIOR

PARITY_SAMPLES = 3
PROBE_OUTPUT_STD = 0.05
"""Weights of the probe's output layer (seeded normal): residuals of order 0.1-1, as a trained head's are."""

ProgressFn = Callable[[str, float, dict], None]


def _replace_entry(files: list[BundleFile], entry: BundleFile) -> list[BundleFile]:
    return [f for f in files if f.role != entry.role] + [entry]


def add_gaussians(bundle_dir: str | Path, ply_path: str | Path) -> dict:
    """Copy a 3DGS PLY into the bundle (read and re-written, so a bad file is refused) and list it; returns the
    manifest."""
    root = Path(bundle_dir)
    b = load_bundle(root, verify=False)
    g = read_ply(ply_path)
    write_ply(root / GAUSSIANS_FILE, g)
    files = _replace_entry(list(b.files.values()), describe_file(root, GAUSSIANS_FILE, ROLE_GAUSSIANS))
    manifest = dict(b.manifest)
    splat = dict(manifest.get("splat") or {})
    splat.update({"gaussians": len(g), "sh_degree": g.sh_degree})
    manifest["splat"] = splat
    return write_manifest(root, manifest, files, version=b.format_version)


class _InitGraph:
    """Built lazily (torch is imported only by the export command)."""

    @staticmethod
    def make(initializer, size_hw: tuple[int, int]):
        import torch

        height, width = size_hw

        class InitGraph(torch.nn.Module):
            def __init__(self) -> None:
                super().__init__()
                self.adapter = initializer.adapter
                self.head = initializer.head

            def forward(self, features: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
                return self.head(self.adapter(features, height, width), prior)

        return InitGraph().eval()


def export_initializer_onnx(
    graph, size_hw: tuple[int, int], feature_channels: int, prior_channels: int, out_path: Path
) -> None:
    import torch

    h, w = size_hw
    example = (
        torch.zeros((1, feature_channels, h // OUTPUT_STRIDE, w // OUTPUT_STRIDE)),
        torch.zeros((1, prior_channels, h, w)),
    )
    with atomic_path(out_path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logging.getLogger("torch.onnx").setLevel(logging.ERROR)
        torch.onnx.export(
            graph,
            example,
            str(tmp),
            dynamo=True,
            external_data=False,
            opset_version=18,
            input_names=list(INIT_INPUTS),
            output_names=[INIT_OUTPUT],
            verbose=False,
        )


def _session(path: Path):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.log_severity_level = 3
    return ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])


def check_images(
    bundle, size_hw: tuple[int, int], n: int = PARITY_SAMPLES, seed: int = 0
) -> tuple[list[np.ndarray], str]:
    """Grayscale (H, W) uint8 images for the checks: the bundle scene's test (or train) images when it is
    where the manifest says, else random noise; and which it was."""
    from acesplat.core.scene import read_split
    from export.bundle_export import evenly
    from export.checks import prepare_frames

    scene = Path(bundle.scene_path) if bundle.scene_path else None
    for split in ("test", "train"):
        if scene is not None and (scene / split).is_dir():
            frames = evenly(read_split(scene, split).frames, n)
            return [f.gray for f in prepare_frames(frames, size_hw)], f"{split} images"
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, size_hw).astype(np.uint8) for _ in range(n)], "random images"


def _priors(size_hw: tuple[int, int], prior_channels: int, n: int, seed: int = 0) -> list[np.ndarray]:
    """Random priors at the scale of real ones (colours, normalised centres and log depths are all O(1))."""
    rng = np.random.default_rng(seed)
    return [rng.normal(0.0, 0.5, (1, prior_channels, *size_hw)).astype(np.float32) for _ in range(n)]


def initializer_parity(graph, onnx_path: Path, features: list[np.ndarray], priors: list[np.ndarray]) -> dict:
    """Largest |ONNX - torch| of the residuals on the same inputs: features (1, C, h, w), priors (1, P, H, W)."""
    import torch

    sess = _session(onnx_path)
    worst, scale = 0.0, 0.0
    for f, p in zip(features, priors):
        got = sess.run([INIT_OUTPUT], {INIT_INPUTS[0]: f, INIT_INPUTS[1]: p})[0]
        with torch.no_grad():
            ref = graph(torch.from_numpy(f), torch.from_numpy(p)).numpy()
        worst = max(worst, float(np.max(np.abs(got - ref))))
        scale = max(scale, float(np.max(np.abs(ref))))
    return {"max_abs_diff": worst, "max_abs_output": scale, "samples": len(features)}


def untrained(init) -> bool:
    """The head's output layer is all zeros (as a fresh head's is): its residuals are zero whatever comes in, so
    comparing the shipped graph with torch cannot show an error in the layers before it."""
    out = init.head.out
    return not bool(out.weight.detach().any()) and not bool(out.bias.detach().any())


def probe_parity(initializer, size_hw: tuple[int, int], features: list[np.ndarray], priors: list[np.ndarray]) -> dict:
    """``initializer_parity`` of a copy of the initializer whose output layer has seeded random weights, exported
    the same way: the export path (adapter, head, their shapes at this size) checked where the shipped head's zero
    output hides it."""
    import copy
    import tempfile

    import torch

    probe = copy.deepcopy(initializer)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        w = probe.head.out.weight
        w.copy_(torch.randn(w.shape, generator=gen) * PROBE_OUTPUT_STD)
    graph = _InitGraph.make(probe, size_hw)
    with tempfile.TemporaryDirectory() as td, torch.no_grad():
        path = Path(td) / "probe.onnx"
        export_initializer_onnx(graph, size_hw, features[0].shape[1], priors[0].shape[1], path)
        return initializer_parity(graph, path, features, priors)


def initializer_through_scr(
    net, graph, init_path: Path, scr_path: Path, images: list[np.ndarray], priors: list[np.ndarray]
) -> dict:
    """What the edge computes (the bundle's SCR graph's features into the ONNX initializer) against torch
    (encoder, adapter and head) from the same images and priors."""
    import torch

    from export.checks import onnx_outputs, torch_features

    scr, init = _session(scr_path), _session(init_path)
    worst, total, count, scale = 0.0, 0.0, 0, 0.0
    for gray, p in zip(images, priors):
        _, feats = onnx_outputs(scr, gray, features=True)
        if feats is None:
            raise InputError(scr_path, "SCR graph has no 'features' output (bundle format 1); re-export the bundle")
        got = init.run([INIT_OUTPUT], {INIT_INPUTS[0]: feats[None], INIT_INPUTS[1]: p})[0]
        with torch.no_grad():
            ref = graph(torch.from_numpy(torch_features(net, gray)[None]), torch.from_numpy(p)).numpy()
        d = np.abs(got - ref)
        worst, total, count = max(worst, float(d.max())), total + float(d.sum()), count + d.size
        scale = max(scale, float(np.max(np.abs(ref))))
    return {
        "max_abs_diff": worst,
        "mean_abs_diff": total / max(count, 1),
        "max_abs_output": scale,
        "samples": len(images),
    }


def _check_bundle_takes_features(root: Path, b, splat_dir: Path, sm: dict, init, net) -> None:
    """The initializer must get the features it was trained on, in the shape the bundle's SCR graph gives."""
    feats = b.scr.get("features")
    if not isinstance(feats, dict) or "shape" not in feats:
        raise InputError(
            root / "manifest.json",
            f"bundle format {b.format_version}: its SCR graph has no features "
            "output for the initializer; re-export the bundle (acesplat export MAP --splat SPLAT)",
        )
    if b.output_stride != OUTPUT_STRIDE:
        raise InputError(
            root / "manifest.json",
            f"the bundle's SCR graph predicts every {b.output_stride}th pixel; the "
            f"initializer takes stride-{OUTPUT_STRIDE} features: export without --dense to add Gaussians",
        )
    channels = int(feats["shape"][1])
    if channels != init.adapter.cfg.in_channels or net.encoder.cfg.out != init.adapter.cfg.in_channels:
        raise InputError(
            splat_dir,
            f"adapter takes {init.adapter.cfg.in_channels} channels, the bundle's SCR graph "
            f"gives {channels} and the map's encoder {net.encoder.cfg.out}",
        )
    bundle_enc = (b.scr.get("encoder") or {}).get("sha256")
    splat_enc = (sm.get("encoder") or {}).get("sha256")
    if bundle_enc and splat_enc and bundle_enc != splat_enc:
        raise InputError(
            splat_dir,
            f"splat was trained on features of encoder {splat_enc[:12]}..., the bundle's SCR "
            f"graph gives encoder {bundle_enc[:12]}...'s",
        )


def export_splat(
    bundle_dir: str | Path,
    splat_dir: str | Path,
    map_path: str | Path,
    encoder_path: str | Path | None = None,
    progress: ProgressFn | None = None,
) -> dict:
    """Add ``splat_dir``'s Gaussians and initializer to the bundle (checked with ``map_path``'s encoder in torch);
    returns the manifest, the seconds and the checks."""
    import torch

    from acesplat.core.bundle import PRECISION_ROLES
    from acesplat.scr.mapfile import encoder_for_map, load_map
    from acesplat.splat.splatfile import PLY_NAME, load_initializer, load_manifest
    from export.checks import torch_features

    t0 = time.monotonic()
    root, splat_dir = Path(bundle_dir), Path(splat_dir)
    sm = load_manifest(splat_dir)
    init = load_initializer(splat_dir)
    m = load_map(map_path)
    net = m.network(encoder_for_map(m, Path(map_path), Path(encoder_path) if encoder_path else None)).eval()
    b = load_bundle(root, verify=False)
    _check_bundle_takes_features(root, b, splat_dir, sm, init, net)
    size = b.input_size
    cells = (size[0] // OUTPUT_STRIDE, size[1] // OUTPUT_STRIDE)
    channels = init.adapter.cfg.in_channels
    if progress:
        progress("splat gaussians", 0.0, {})
    manifest = add_gaussians(root, splat_dir / PLY_NAME)
    if progress:
        progress("splat gaussians", 1.0, {})
        progress("splat initializer", 0.0, {})
    graph = _InitGraph.make(init, size)
    with torch.no_grad():
        export_initializer_onnx(graph, size, channels, PRIOR_CHANNELS, root / INIT_FILE)
    if progress:
        progress("splat initializer", 1.0, {})
        progress("check splat initializer", 0.0, {})
    images, source = check_images(b, size)
    priors = _priors(size, PRIOR_CHANNELS, len(images))
    features = [torch_features(net, g)[None] for g in images]
    parity = initializer_parity(graph, root / INIT_FILE, features, priors)
    parity["images"] = source
    parity["untrained_head"] = untrained(init)
    checks = dict(b.manifest.get("checks") or {})
    checks["splat_init_fp32_vs_torch"] = parity
    checks.pop("splat_init_probe_fp32_vs_torch", None)
    if parity["untrained_head"]:
        probe = probe_parity(init, size, features, priors)
        probe["images"] = source
        checks["splat_init_probe_fp32_vs_torch"] = probe
    for precision, role in PRECISION_ROLES.items():
        if b.has(role):
            via = initializer_through_scr(net, graph, root / INIT_FILE, b.path(role), images, priors)
            via["images"] = source
            checks[f"splat_init_via_scr_{precision}_vs_torch"] = via
    if progress:
        progress("check splat initializer", 1.0, parity)
    b = load_bundle(root, verify=False)
    files = _replace_entry(list(b.files.values()), describe_file(root, INIT_FILE, ROLE_SPLAT_INIT))
    head = init.head.cfg
    splat = dict(manifest.get("splat") or {})
    splat.update(
        {
            "source": str(splat_dir.resolve()),
            "background": sm.get("background", [0.0, 0.0, 0.0]),
            "short_side": sm.get("short_side"),
            "scene_norm": sm.get("scene_norm"),
            "encoder": sm.get("encoder"),
            "adapter": init.adapter.cfg.as_dict(),
            "head": head.as_dict(),
            "init": {
                "input_size": [size[0], size[1]],
                "inputs": {
                    INIT_INPUTS[0]: [1, channels, cells[0], cells[1]],
                    INIT_INPUTS[1]: [1, PRIOR_CHANNELS, size[0], size[1]],
                },
                "output": {INIT_OUTPUT: [1, head.out_channels, size[0], size[1]]},
                "features": f"the SCR graph's '{SCR_FEATURES_OUTPUT}' output of the same frame (either precision)",
                "prior": "rgb - 0.5 (3), (world centre - scene_norm.centre) / scene_norm.scale (3), "
                "log(depth / scene_norm.scale) (1)",
                "residuals": f"opacity logit (1), SH (3 x {(head.sh_degree + 1) ** 2}, coefficient-major), "
                "log-scale (3), quaternion wxyz (4)",
                "opacity_prior": OPACITY_PRIOR,
                "scale_prior": SCALE_PRIOR,
                "precision": "fp32",
            },
        }
    )
    new_manifest = dict(b.manifest)
    new_manifest["splat"] = splat
    new_manifest["checks"] = checks
    written = write_manifest(root, new_manifest, files)
    return {
        "manifest": written,
        "seconds": time.monotonic() - t0,
        "parity": parity,
        "checks": {k: v for k, v in checks.items() if k.startswith("splat_init")},
    }
