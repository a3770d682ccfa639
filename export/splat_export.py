"""Add a splat folder's Gaussian models to a bundle: the Gaussians (PLY) and the initializer as ONNX.

The initializer is one static-shape graph: grayscale image (1, 1, H, W) in [0, 255] and the init
head's prior (1, PRIOR_CHANNELS, H, W) in, head residuals (1, C, H, W) out, with the map's SCR
encoder, the feature adapter and the init head inside (the bundle's SCR graph outputs coordinates
only, so the edge cannot feed the adapter the encoder's features otherwise). FP32 only: no INT8
twin is written (it would need its own quality check on rendered Gaussians).

Files are written into the finished bundle and only then listed in its manifest (rewritten
atomically), so an interrupted run leaves the bundle as it was, plus at most an unlisted file.
The role names are the ones edge/refine/bundle_models.py reads.
"""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path
from typing import Callable

import numpy as np

from acesplat.core.atomic import atomic_path
from acesplat.core.bundle import BundleFile, describe_file, load_bundle, write_manifest
from acesplat.core.errors import InputError
from acesplat.core.ply import read_ply, write_ply

ROLE_GAUSSIANS = "gaussians"
ROLE_SPLAT_INIT = "splat_init_fp32"
GAUSSIANS_FILE = "gaussians.ply"
INIT_FILE = "splat_init.onnx"
INIT_INPUTS = ("gray", "prior")
INIT_OUTPUT = "raw"
PARITY_SAMPLES = 3

ProgressFn = Callable[[str, float, dict], None]


def _replace_entry(files: list[BundleFile], entry: BundleFile) -> list[BundleFile]:
    return [f for f in files if f.role != entry.role] + [entry]


def add_gaussians(bundle_dir: str | Path, ply_path: str | Path) -> dict:
    """Copy a 3DGS PLY into the bundle (read and re-written, so a bad file is refused) and list it; returns the manifest."""
    root = Path(bundle_dir)
    b = load_bundle(root, verify=False)
    g = read_ply(ply_path)
    write_ply(root / GAUSSIANS_FILE, g)
    files = _replace_entry(list(b.files.values()), describe_file(root, GAUSSIANS_FILE, ROLE_GAUSSIANS))
    manifest = dict(b.manifest)
    splat = dict(manifest.get("splat") or {})
    splat.update({"gaussians": len(g), "sh_degree": g.sh_degree})
    manifest["splat"] = splat
    return write_manifest(root, manifest, files)


class _InitGraph:
    """Built lazily (torch is imported only by the export command)."""

    @staticmethod
    def make(network, initializer):
        import torch

        from acesplat.scr.network import normalize_gray

        class InitGraph(torch.nn.Module):
            def __init__(self) -> None:
                super().__init__()
                self.encoder = network.encoder
                self.adapter = initializer.adapter
                self.head = initializer.head

            def forward(self, gray: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
                feats = self.encoder(normalize_gray(gray))
                up = self.adapter(feats, gray.shape[2], gray.shape[3])
                return self.head(up, prior)

        return InitGraph().eval()


def export_initializer_onnx(graph, size_hw: tuple[int, int], prior_channels: int, out_path: Path) -> None:
    import torch

    h, w = size_hw
    example = (torch.full((1, 1, h, w), 128.0), torch.zeros((1, prior_channels, h, w)))
    with atomic_path(out_path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logging.getLogger("torch.onnx").setLevel(logging.ERROR)
        torch.onnx.export(graph, example, str(tmp), dynamo=True, external_data=False, opset_version=18,
                          input_names=list(INIT_INPUTS), output_names=[INIT_OUTPUT], verbose=False)


def initializer_parity(graph, onnx_path: Path, size_hw: tuple[int, int], prior_channels: int, seed: int = 0) -> dict:
    """Largest |ONNX - torch| of the residuals on random images and priors (priors at the scale of real ones)."""
    import onnxruntime as ort
    import torch

    so = ort.SessionOptions()
    so.log_severity_level = 3
    sess = ort.InferenceSession(str(onnx_path), sess_options=so, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(seed)
    h, w = size_hw
    worst, scale = 0.0, 0.0
    for _ in range(PARITY_SAMPLES):
        gray = rng.integers(0, 256, (1, 1, h, w)).astype(np.float32)
        prior = rng.normal(0.0, 0.5, (1, prior_channels, h, w)).astype(np.float32)
        got = sess.run([INIT_OUTPUT], {INIT_INPUTS[0]: gray, INIT_INPUTS[1]: prior})[0]
        with torch.no_grad():
            ref = graph(torch.from_numpy(gray), torch.from_numpy(prior)).numpy()
        worst = max(worst, float(np.max(np.abs(got - ref))))
        scale = max(scale, float(np.max(np.abs(ref))))
    return {"max_abs_diff": worst, "max_abs_output": scale, "samples": PARITY_SAMPLES}


def export_splat(bundle_dir: str | Path, splat_dir: str | Path, map_path: str | Path,
                 encoder_path: str | Path | None = None, progress: ProgressFn | None = None) -> dict:
    """Add ``splat_dir``'s Gaussians and initializer (with ``map_path``'s encoder) to the bundle; returns the manifest."""
    import torch

    from acesplat.scr.mapfile import encoder_for_map, load_map
    from acesplat.splat.init_head import OPACITY_PRIOR, PRIOR_CHANNELS, SCALE_PRIOR
    from acesplat.splat.splatfile import PLY_NAME, load_initializer, load_manifest

    t0 = time.monotonic()
    root, splat_dir = Path(bundle_dir), Path(splat_dir)
    sm = load_manifest(splat_dir)
    init = load_initializer(splat_dir)
    m = load_map(map_path)
    net = m.network(encoder_for_map(m, Path(map_path), Path(encoder_path) if encoder_path else None)).eval()
    b = load_bundle(root, verify=False)
    if net.encoder.cfg.out != init.adapter.cfg.in_channels:
        raise InputError(splat_dir, f"adapter takes {init.adapter.cfg.in_channels} channels, the map's encoder gives {net.encoder.cfg.out}")
    size = b.input_size
    if progress:
        progress("splat gaussians", 0.0, {})
    manifest = add_gaussians(root, splat_dir / PLY_NAME)
    if progress:
        progress("splat gaussians", 1.0, {})
        progress("splat initializer", 0.0, {})
    graph = _InitGraph.make(net, init)
    with torch.no_grad():
        export_initializer_onnx(graph, size, PRIOR_CHANNELS, root / INIT_FILE)
    parity = initializer_parity(graph, root / INIT_FILE, size, PRIOR_CHANNELS)
    if progress:
        progress("splat initializer", 1.0, parity)
    b = load_bundle(root, verify=False)
    files = _replace_entry(list(b.files.values()), describe_file(root, INIT_FILE, ROLE_SPLAT_INIT))
    head = init.head.cfg
    splat = dict(manifest.get("splat") or {})
    splat.update({
        "source": str(splat_dir.resolve()),
        "background": sm.get("background", [0.0, 0.0, 0.0]),
        "short_side": sm.get("short_side"),
        "scene_norm": sm.get("scene_norm"),
        "adapter": init.adapter.cfg.as_dict(),
        "head": head.as_dict(),
        "init": {
            "input_size": [size[0], size[1]],
            "inputs": {INIT_INPUTS[0]: [1, 1, size[0], size[1]], INIT_INPUTS[1]: [1, PRIOR_CHANNELS, size[0], size[1]]},
            "output": {INIT_OUTPUT: [1, head.out_channels, size[0], size[1]]},
            "prior": "rgb - 0.5 (3), (world centre - scene_norm.centre) / scene_norm.scale (3), log(depth / scene_norm.scale) (1)",
            "residuals": f"opacity logit (1), SH (3 x {(head.sh_degree + 1) ** 2}, coefficient-major), log-scale (3), quaternion wxyz (4)",
            "opacity_prior": OPACITY_PRIOR,
            "scale_prior": SCALE_PRIOR,
            "precision": "fp32",
        },
    })
    checks = dict(b.manifest.get("checks") or {})
    checks["splat_init_fp32_vs_torch"] = parity
    new_manifest = dict(b.manifest)
    new_manifest["splat"] = splat
    new_manifest["checks"] = checks
    written = write_manifest(root, new_manifest, files)
    return {"manifest": written, "seconds": time.monotonic() - t0, "parity": parity}
