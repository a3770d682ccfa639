"""Stage 2 end to end: posed frames + a frozen SCR network -> an optimised Gaussian scene set.

Order (all inside one wall-clock budget): read the views at the map's resolution; run the SCR
network once per initialisation view (features kept); keep trustworthy cells; seed the scene set; optimise it.
The default ``start`` ("cells") seeds 3DGS's point start at the ``seed_cells`` most textured trusted cells. With
``start`` "head": optionally train the adapter and init head alone for ``head_warmup`` of the budget (by default
not: the fresh head's analytic start, the SCR coordinates at pixel resolution with the pixels' colours), merge
every view's head Gaussians into one scene set on a lattice whose stride fits ``max_initial``, and optimise the
set (with ``joint_head``, the head with it). The adapter and head are built and saved either way: the export
ships them as the edge refiner's initializer.

Protocols: ``static`` reconstructs the captured (training) views; ``sparse`` starts from two training
views only and holds out the training frames between them as targets.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from acesplat.align.keyframe_set import triangulated_points
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.scene import Frame
from acesplat.splat.adapter import AdapterConfig
from acesplat.splat.head_training import HeadTrainer
from acesplat.splat.init_head import InitHeadConfig
from acesplat.splat.instantiate import GaussianInitializer, merge_views
from acesplat.splat.optimize import EvalFn, OptimizeConfig, OptimizeResult, optimise_gaussians
from acesplat.splat.params import GaussianParams, params_from_gaussians, params_from_tensors
from acesplat.splat.point_init import gaussians_from_points
from acesplat.splat.schedule import NET_LR_MAX, NET_LR_MIN, one_cycle
from acesplat.splat.views import SplatView, load_views, run_scr
from acesplat.splatcore.cell_seeds import cell_points, cell_texture, textured_cells
from acesplat.splatcore.fusion import DEPTH_TOLERANCE
from acesplat.splatcore.head_io import SceneNorm
from acesplat.splatcore.validity import (
    CROSS_VIEW_NEIGHBOURS,
    CROSS_VIEW_TOLERANCE,
    ValidityConfig,
    confirm_across_views,
)

PROTOCOLS = ("static", "sparse")
SPARSE_GAP = 4
"""Default sparse-view pair: two training frames this many frames apart around the middle of the sequence."""
MIN_VALID_FRACTION = 0.02
"""Below this share of trustworthy SCR cells the map does not describe the scene."""
HEAD_WARMUP_DIVISOR = 5
"""Without head_iterations, the head's warm-up takes a fifth as many steps as the scene set's iterations."""
SCENE_EXTENT_FACTOR = 1.1
"""3DGS's scene extent: 1.1 x the largest camera distance from their mean."""

ProgressFn = Callable[[str, float, dict], None]
STARTS = ("cells", "corners", "head")


@dataclass
class SplatConfig:
    iterations: int = knob(
        knob_default(OptimizeConfig, "iterations"), "Optimisation iterations (fixed work: the same set on every CPU)."
    )
    minutes: float | None = knob(
        None, "Optional wall-clock cap on Stage 2; a run it cuts short is flagged cut_short (and warned about)."
    )
    protocol: str = knob(
        "static", "static (reconstruct the captured views) or sparse (two views in, held-out targets)."
    )
    head_iterations: int | None = knob(
        None, "Head warm-up steps when head_warmup > 0 (None: a fifth of the iterations)."
    )
    sh_degree: int = knob(knob_default(OptimizeConfig, "sh_degree"), "Highest SH degree of the scene set.")
    start: str = knob(
        "corners",
        "Where Gaussians start: corners (each view's corners triangulated between the views, the head's depth their "
        "first guess: level with SIFT points on real photographs, ahead of cells on test views), cells (the most "
        "textured trusted SCR cells, 3DGS's point start) or head (the init head's Gaussians at pixel resolution, "
        "views fused); bench/splat_init.md.",
    )
    seed_cells: int = knob(12_000, "Cells the 'cells' start seeds (as many points as a sparse SfM start has).")
    seed_corners: int = knob(
        1200,
        "Corners per view the 'corners' start triangulates between views (about as many seeds as SIFT's on "
        "herzjesu25; 800 started 0.3-0.5 dB lower: bench/splat_init.md).",
    )
    max_initial: int = knob(60_000, "Budget of initial Gaussians: the seeding lattice's stride is chosen to fit it.")
    max_gaussians: int = knob(
        200_000, "Cap on the number of Gaussians (rendering time, hence CPU time, grows with it)."
    )
    init_views: int = knob(48, "At most this many training views (evenly spread) seed Gaussians; all of them train.")
    head_warmup: float = knob(
        0.0,
        "Above 0, the adapter and head train alone before seeding, for head_iterations steps (under a cap, at most "
        "this share of it; 0: the head's analytic start, better in the same time: bench/splat_init.md).",
    )
    joint_head: bool = knob(
        False, "Keep training the head jointly with the scene set (its renders cost the scene set iterations)."
    )
    fuse: bool = knob(True, "Seed only the pixels no earlier view already seeded (one layer per surface).")
    fusion_tolerance: float = knob(
        DEPTH_TOLERANCE, "Relative depth difference under which views see the same surface (SCR depths are noisy)."
    )
    fill: bool = knob(
        False,
        "Also seed untrusted pixels, at the depth of the nearest trusted cell (on real photographs that puts Gaussians "
        "in front of sky and street: bench/splat_init.md).",
    )
    cross_view: int = knob(
        CROSS_VIEW_NEIGHBOURS, "Confirm trusted cells against this many nearest views (0: own-view reprojection only)."
    )
    cross_view_tol: float = knob(
        CROSS_VIEW_TOLERANCE, "Relative depth agreement with a neighbouring view's prediction that confirms a cell."
    )
    sparse_views: tuple[int, int] | None = knob(None, "Sparse protocol: the two training frame indices, e.g. 10,14.")
    validity: ValidityConfig = knob(reason="Which SCR cells become Gaussian centres.", factory=ValidityConfig)
    adapter_widths: tuple[int, int, int, int] = knob(
        knob_default(AdapterConfig, "widths"), "Feature adapter widths at 1/8, 1/4, 1/2 and full resolution."
    )
    head: InitHeadConfig = knob(reason="The init head.", factory=InitHeadConfig)
    opacity_reset: bool = knob(knob_default(OptimizeConfig, "opacity_reset"), "Reset opacities on 3DGS's schedule.")
    densify: bool = knob(knob_default(OptimizeConfig, "densify"), "Clone and split Gaussians on schedule.")
    seed: int = knob(0, "Seed of view sampling, seeding offsets and initialisation.")

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise InputError(None, f"protocol must be one of {PROTOCOLS}, got {self.protocol!r}")
        if self.minutes is not None and self.minutes <= 0:
            raise InputError(None, f"minutes must be positive, got {self.minutes}")
        if self.iterations < 0 or (self.head_iterations is not None and self.head_iterations < 0):
            raise InputError(None, f"iterations must be >= 0, got {self.iterations}, {self.head_iterations}")
        if self.start not in STARTS:
            raise InputError(None, f"start must be one of {STARTS}, got {self.start!r}")
        if self.start != "head" and (self.head_warmup > 0 or self.joint_head):
            raise InputError(
                None,
                "head_warmup and joint_head train the init head, which seeds with start 'head' only (use --start head)",
            )
        if self.seed_cells < 2 or self.seed_corners < 4:
            raise InputError(
                None, f"seed_cells must be at least 2 and seed_corners 4, got {self.seed_cells}, {self.seed_corners}"
            )


@dataclass
class SplatResult:
    params: GaussianParams
    initializer: GaussianInitializer
    norm: SceneNorm
    train_views: list[SplatView]
    target_frames: list[Frame]
    stats: dict
    optimize: OptimizeResult


def protocol_split(n_frames: int, protocol: str, pair: tuple[int, int] | None = None) -> tuple[list[int], list[int]]:
    """(training frame indices, held-out target indices) of a protocol over ``n_frames`` training frames."""
    if protocol == "static":
        return list(range(n_frames)), []
    if n_frames < 2:
        raise InputError(None, f"the sparse protocol needs at least 2 training frames, the scene has {n_frames}")
    if pair is None:
        gap = min(SPARSE_GAP, n_frames - 1)
        a = max(0, (n_frames - 1 - gap) // 2)
        pair = (a, a + gap)
    a, b = sorted(int(i) for i in pair)
    if a == b or a < 0 or b >= n_frames:
        raise InputError(None, f"sparse views must be two different training frames in 0..{n_frames - 1}, got {pair}")
    return [a, b], list(range(a + 1, b))


def spread(n: int, k: int) -> list[int]:
    """k (or n) indices evenly spread over range(n)."""
    if n <= k:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})


def scene_extent(poses: np.ndarray, fallback: float) -> float:
    c = np.asarray(poses)[:, :3, 3]
    r = float(np.max(np.linalg.norm(c - c.mean(0), axis=1))) if len(c) else 0.0
    return SCENE_EXTENT_FACTOR * max(r, fallback)


def splat_scene(
    frames: Sequence[Frame],
    network: torch.nn.Module,
    short_side: int,
    cfg: SplatConfig,
    source: str | Path | None = None,
    progress: ProgressFn | None = None,
    eval_fn: EvalFn | None = None,
    eval_every_s: float | None = None,
) -> SplatResult:
    """Run Stage 2 on the training ``frames`` with the frozen SCR ``network`` (encoder + head).

    ``source`` names the map in errors (a map that does not fit the scene is bad input).
    """
    t0 = time.monotonic()
    budget = None if cfg.minutes is None else cfg.minutes * 60.0
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    train_idx, target_idx = protocol_split(len(frames), cfg.protocol, cfg.sparse_views)
    views = load_views([frames[i] for i in train_idx], short_side)
    init_views = [views[i] for i in spread(len(views), cfg.init_views)]
    run_scr(
        init_views,
        network,
        cfg.validity,
        keep_features=True,
        progress=(lambda d, n: progress("scr", d / n, {"views": d})) if progress else None,
    )
    fractions = [v.validity.fraction for v in init_views]  # type: ignore[union-attr]
    overall = float(np.mean(fractions))
    usable = [v for v, f in zip(init_views, fractions) if f > 0]
    if not usable or overall < MIN_VALID_FRACTION:
        vc = cfg.validity
        raise InputError(
            source,
            f"validity mask is {'empty' if not usable else f'{overall:.1%} full'}: the map's scene coordinates do not "
            f"reproject within {vc.reproj_max_px:g} px at depths {vc.depth_min:g}..{vc.depth_max:g} m in this scene's "
            "training views (a map of another scene, other images or another encoder?)",
        )
    own_valid = int(sum(int(v.validity.valid.sum()) for v in usable))  # type: ignore[union-attr]
    if cfg.cross_view > 0 and len(usable) > 1:
        confirmed = confirm_across_views(
            [v.coords for v in usable],
            [v.validity.valid for v in usable],  # type: ignore[union-attr]
            [v.pose for v in usable],
            [v.intrinsics for v in usable],
            cfg.cross_view,
            cfg.cross_view_tol,
        )
        for v, c in zip(usable, confirmed):
            v.validity = dataclasses.replace(v.validity, valid=c)  # type: ignore[arg-type]
        usable = [v for v in usable if v.validity.valid.any()]  # type: ignore[union-attr]
        if not usable:
            raise InputError(
                source, "validity mask is empty: no view's scene coordinates agree with its neighbours' depths"
            )
    confirmed_cells = int(sum(int(v.validity.valid.sum()) for v in usable))  # type: ignore[union-attr]
    depths = np.concatenate([_valid_depths(v) for v in usable])
    norm = SceneNorm.from_views(np.stack([v.pose[:3, 3] for v in views]), depths)
    extent = scene_extent(np.stack([v.pose for v in views]), fallback=0.1 * norm.scale)

    adapter_cfg = AdapterConfig(in_channels=int(usable[0].features.shape[1]), widths=cfg.adapter_widths)  # type: ignore[union-attr]
    initializer = GaussianInitializer(adapter_cfg, cfg.head)
    head = HeadTrainer(
        initializer, usable, norm, cfg.sh_degree, fill=cfg.fill, max_depth_ratio=cfg.validity.max_depth_ratio
    )
    t_prep = time.monotonic() - t0
    warm_deadline = None if budget is None else time.monotonic() + cfg.head_warmup * budget
    warm_steps, warm_skipped = _warm_up(head, cfg, warm_deadline, rng, progress)
    t_warm = time.monotonic() - t0 - t_prep

    seeding: dict = {"start": cfg.start}
    if cfg.start == "cells":
        params = _cell_start(usable, cfg, source)
        seeding["seed_cells"] = int(params["means"].shape[0])
    elif cfg.start == "corners":
        params, per_view = _corner_start(usable, frames, network, short_side, cfg, source)
        seeding.update(seed_corners=int(params["means"].shape[0]), seed_corners_per_view=per_view)
    else:
        pixels = [head.pixels(i) for i in range(len(usable))]
        tensors, merge = merge_views(
            usable,
            pixels,
            initializer,
            cfg.max_initial,
            cfg.sh_degree,
            rng,
            fuse=cfg.fuse,
            depth_tol=cfg.fusion_tolerance,
        )
        if not tensors:
            raise InputError(
                source, "validity mask is empty at pixel resolution in every view (no Gaussian to start from)"
            )
        params = params_from_tensors(tensors)
        seeding.update(
            trusted_pixels=int(sum(int(p.trusted.sum()) for p in pixels)),
            seeding_pixels=int(sum(int(p.valid.sum()) for p in pixels)),
            novel_pixels=merge.novel_pixels,
            stride=merge.stride,
        )
    n_initial = int(params["means"].shape[0])
    remaining = None if budget is None else max(budget - (time.monotonic() - t0), 1.0)
    ocfg = OptimizeConfig(
        scene_extent=extent,
        max_gaussians=max(cfg.max_gaussians, n_initial),
        sh_degree=cfg.sh_degree,
        iterations=cfg.iterations,
        opacity_reset=cfg.opacity_reset,
        densify=cfg.densify,
        head_every=knob_default(OptimizeConfig, "head_every") if cfg.joint_head else 0,
        seed=cfg.seed,
    )
    opt = optimise_gaussians(
        params,
        views,
        ocfg,
        remaining,
        head=head if cfg.joint_head else None,
        progress=progress,
        eval_fn=eval_fn,
        eval_every_s=eval_every_s,
    )
    stats = {
        "protocol": cfg.protocol,
        "seconds": time.monotonic() - t0,
        "prepare_seconds": t_prep,
        "head_warmup_seconds": t_warm,
        "optimise_seconds": opt.seconds,
        "train_views": [v.name for v in views],
        "init_views": len(init_views),
        "init_views_used": len(usable),
        "valid_cell_fraction": overall,
        "valid_cells": own_valid,
        "confirmed_cells": confirmed_cells,
        **seeding,
        "gaussians_initial": n_initial,
        "gaussians_final": int(params["means"].shape[0]),
        "iterations": opt.iterations,
        "iterations_planned": opt.iterations_planned,
        "minutes_cap": cfg.minutes,
        "cut_short": opt.iterations < opt.iterations_planned,
        "head_warmup_steps": warm_steps,
        "head_steps": opt.head_steps,
        "skipped_steps": opt.skipped_steps + warm_skipped,
        "scene_extent": extent,
        "scene_norm": norm.as_dict(),
        "image_size": list(views[0].size),
        "schedule": opt.schedule.as_dict(),
        "lifecycle": opt.events,
    }
    return SplatResult(params, initializer, norm, views, [frames[i] for i in target_idx], stats, opt)


def _cell_start(views: Sequence[SplatView], cfg: SplatConfig, source: str | Path | None) -> GaussianParams:
    """3DGS's point start from the ``cfg.seed_cells`` most textured trusted cells of ``views``."""
    masks = textured_cells(
        [cell_texture(v.gray, v.validity.valid.shape) for v in views],  # type: ignore[union-attr]
        [v.validity.valid for v in views],  # type: ignore[union-attr]
        cfg.seed_cells,
    )
    parts = [cell_points(v.coords, m, v.rgb) for v, m in zip(views, masks)]  # type: ignore[arg-type]
    points = np.concatenate([p for p, _ in parts])
    if len(points) < 2:
        raise InputError(source, f"only {len(points)} trusted cell(s) to start from: nothing to seed Gaussians with")
    return params_from_gaussians(gaussians_from_points(points, np.concatenate([c for _, c in parts]), cfg.sh_degree))


def _corner_start(
    views: Sequence[SplatView],
    frames: Sequence[Frame],
    network: torch.nn.Module,
    short_side: int,
    cfg: SplatConfig,
    source: str | Path | None,
) -> tuple[GaussianParams, list[int]]:
    """3DGS's point start from each view's corners triangulated between the views (keyframe_set.triangulated_points),
    the views made keyframes as the alignment makes them (acesplat.scr.keyframes: the head's depth re-measured
    between neighbours, the corners' first guess); and how many each view gave."""
    from acesplat.core.scene import SceneSplit
    from acesplat.scr.keyframes import MapKeyframes

    by_name = {f.name: f for f in frames}
    kfs = MapKeyframes(SceneSplit(Path(source or "."), "train", [by_name[v.name] for v in views]), network, short_side)
    keyframes = [kfs.keyframe(i) for i in range(len(views))]
    points, colours, per_view = triangulated_points(keyframes, [v.rgb for v in views], cfg.seed_corners)
    if len(points) < 2:
        raise InputError(
            source,
            f"only {len(points)} corner(s) triangulate between the views: nothing to seed Gaussians with "
            "(--start cells seeds from the map's cells alone)",
        )
    return params_from_gaussians(gaussians_from_points(points, colours, cfg.sh_degree)), per_view


def _valid_depths(v: SplatView) -> np.ndarray:
    from acesplat.splatcore.pixel_coords import cell_depths

    assert v.coords is not None and v.validity is not None
    return cell_depths(v.coords.astype(np.float64), v.pose)[v.validity.valid]


def _warm_up(
    head: HeadTrainer, cfg: SplatConfig, deadline: float | None, rng: np.random.Generator, progress: ProgressFn | None
) -> tuple[int, int]:
    """Train the adapter and head alone (their own AdamW and one-cycle) for their steps, or until ``deadline`` (a
    cap, time.monotonic); no step at all with ``cfg.head_warmup`` 0 (the head's analytic start)."""
    from acesplat.splat.optimize import finite_gradients

    if cfg.head_warmup <= 0:
        return 0, 0
    opt = torch.optim.AdamW(head.init.parameters(), lr=NET_LR_MIN, weight_decay=0.01)
    start = time.monotonic()
    planned = cfg.iterations // HEAD_WARMUP_DIVISOR if cfg.head_iterations is None else cfg.head_iterations
    steps = skipped = 0
    while True:
        p = steps / planned if planned else 1.0
        if deadline is not None:
            p = max(p, (time.monotonic() - start) / max(deadline - start, 1e-9))
        if p >= 1.0:
            break
        for g in opt.param_groups:
            g["lr"] = one_cycle(p, NET_LR_MIN, NET_LR_MAX)
        loss = head.loss(rng)
        steps += 1
        if loss is None:
            continue
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if not finite_gradients(opt):
            skipped += 1
            continue
        opt.step()
        if progress:
            progress("head", p, {"step": steps, "loss": float(loss.detach())})
    return steps, skipped
