"""Stage 2 as one call: a splat of a scene's training split seeded by its SCR map, scored and written."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from acesplat.core.errors import InputError

if TYPE_CHECKING:
    from acesplat.splat.pipeline import SplatConfig

TRAIN_PSNR_VIEWS = 25
"""train_psnr is the mean over this many training views spread along the sequence (all of them: `acesplat render`)."""


def _check_map_fits(map_path: Path, short_side: int, frames) -> None:
    """A map built from larger images than these cannot be this scene's map."""
    k = frames[0].intrinsics
    if short_side > min(k.width, k.height):
        raise InputError(
            map_path,
            f"map was built for images with a {short_side} px short side, but the scene's images are "
            f"{k.width}x{k.height} (a map of other images?)",
        )


def run_splat(
    scene: Path,
    map_path: Path,
    out: Path,
    cfg: SplatConfig,
    encoder: Path | None = None,
    device: str = "auto",
    progress: Callable[[str, float, dict], None] | None = None,
) -> dict:
    """Stage 2 as one call (`acesplat splat` and the demo): Stage 2 on ``scene``'s training split seeded
    by ``map_path``, scored, written to the splat folder ``out``; returns the report (the command's JSON)."""
    import torch

    from acesplat.core.scene import read_split
    from acesplat.scr.device import resolve_device
    from acesplat.scr.mapfile import encoder_for_map, load_map
    from acesplat.splat.evaluate import evaluate_views
    from acesplat.splat.params import gaussians_from_params
    from acesplat.splat.pipeline import splat_scene, spread
    from acesplat.splat.splatfile import save_splat
    from acesplat.splat.views import load_views

    dev = resolve_device(device)
    m = load_map(map_path)
    enc = encoder_for_map(m, map_path, encoder)
    train = read_split(scene, "train")
    _check_map_fits(map_path, m.short_side, train.frames)
    net = m.network(enc).to(dev)
    for p in net.parameters():
        p.requires_grad_(False)
    res = splat_scene(train.frames, net, m.short_side, cfg, source=map_path, progress=progress)
    res.initializer.cpu()
    g = gaussians_from_params(res.params)
    t_eval = time.monotonic()
    probe = [res.train_views[i] for i in spread(len(res.train_views), TRAIN_PSNR_VIEWS)]
    ev = evaluate_views(
        g, probe, progress=(lambda d, n: progress("evaluate", d / n, {"views": d})) if progress else None
    )
    targets = None
    if res.target_frames:
        targets = evaluate_views(g, load_views(res.target_frames, m.short_side))
    eval_s = time.monotonic() - t_eval
    s = res.stats
    report = {
        "seconds": s["seconds"],
        "gaussians_initial": s["gaussians_initial"],
        "gaussians_final": s["gaussians_final"],
        "train_psnr": ev["psnr"],
        "train_ssim": ev["ssim"],
        "train_psnr_views": ev["frames"],
        **(
            {"target_psnr": targets["psnr"], "target_ssim": targets["ssim"], "target_frames": targets["frames"]}
            if targets
            else {}
        ),
        "eval_seconds": eval_s,
        "device": dev,
        "torch_threads": torch.get_num_threads(),
        **{k: v for k, v in s.items() if k not in ("seconds", "gaussians_initial", "gaussians_final", "train_views")},
        "history": res.optimize.history,
    }
    manifest = {
        "scene": str(Path(scene).resolve()),
        "map": str(Path(map_path).resolve()),
        "encoder": m.encoder_identity.as_dict(),
        "short_side": m.short_side,
        "background": [0.0, 0.0, 0.0],
        "sh_degree": g.sh_degree,
        "train_views": s["train_views"],
        "target_views": [f.name for f in res.target_frames],
        **{k: v for k, v in report.items() if k != "history"},
    }
    save_splat(out, g, res.initializer, manifest)
    return report
