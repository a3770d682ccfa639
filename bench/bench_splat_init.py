"""The paper's claim, measured: the same Stage 2 budget from three starts, PSNR against wall-clock time.

Starts: SCR initialisation (ours: the map's most textured trusted cells as points, `scr_cells`, or its scene
coordinates through the adapter and init head, `scr*`; SCR_VARIANTS), sparse SIFT points triangulated with the
known poses (the conventional SfM-style start), and 3DGS's random initialisation. Every start gets the same
wall-clock budget, and its own preparation (SCR inference and head warm-up, SIFT matching and triangulation) is
charged to it; with --iterations, every start runs that many iterations instead (the same work, preparation
free). After the start the optimisation is the same code (acesplat.splat.optimize) with the same lifecycle.

Scenes: the built-in synthetic room (synthesized into --out if absent) and ../shared/data/herzjesu25
(read in place). Maps come from --builtin-map / --herzjesu-map, or are made here with Stage 1
(--map-minutes, with the shipped encoder or --encoder); a map made here is reused on the next run.

Quality is sampled every --eval-every seconds of training time on a few training and test views
(the evaluation time is not charged to the budget); at the end every training and test view is
scored. Output: a table, <out>/bench_splat_init.json and <out>/bench_splat_init.png. Results already in
that JSON for starts not run again are kept (so one start can be re-run alone).

    python bench/bench_splat_init.py --minutes 10 --out runs/bench_splat
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from acesplat.align.keyframe_align import Keyframe
from acesplat.align.keyframe_depth import depth_neighbours, refine_depth
from acesplat.core.atomic import atomic_path, write_json
from acesplat.core.config import knob_default
from acesplat.core.geometry import transform_points
from acesplat.core.grid import DENSE_OUTPUT_STRIDE, OUTPUT_STRIDE, cell_centers
from acesplat.core.machine import machine_line
from acesplat.core.scene import read_split
from acesplat.scr.mapping import TrainingImage
from acesplat.scr.novel_views import head_depth
from acesplat.splat.evaluate import evaluate_views
from acesplat.splat.optimize import OptimizeConfig, optimise_gaussians
from acesplat.splat.params import gaussians_from_params, params_from_gaussians
from acesplat.splat.pipeline import SplatConfig, scene_extent, splat_scene, spread
from acesplat.splat.point_init import gaussians_from_points, random_points, triangulated_points
from acesplat.splat.views import SplatView, load_views, run_scr
from acesplat.splatcore.cell_seeds import cell_points, cell_texture
from acesplat.splatcore.validity import cell_validity

REPO = Path(__file__).resolve().parents[1]
HERZJESU = REPO.parent / "shared" / "data" / "herzjesu25"
METHODS = (
    "scr",
    "scr_analytic",
    "scr_analytic_fill",
    "scr_cells",
    "scr_points",
    "scr_points_few",
    "scr_points_texture",
    "sift",
    "scr_corners",
    "scr_corners_lib",
    "scr_corners_1200",
    "scr_corners_2000",
    "scr_corners_cells",
    "scr_corners_gapcells",
    "random",
)
SCR_VARIANTS = {
    "scr": {"start": "head", "head_warmup": 0.08, "joint_head": True, "fill": True},
    "scr_analytic": {"start": "head", "head_warmup": 0.0, "joint_head": False, "fill": False},
    "scr_analytic_fill": {"start": "head", "head_warmup": 0.0, "joint_head": False, "fill": True},
    "scr_cells": {"start": "cells"},
    "scr_corners_lib": {"start": "corners"},
    "scr_corners_800": {"start": "corners", "seed_corners": 800},
    "scr_corners_1200": {"start": "corners", "seed_corners": 1200},
    "scr_corners_2000": {"start": "corners", "seed_corners": 2000},
    "scr_corners_cells": {"start": "corners", "seed_corners": 1200},
    "scr_corners_gapcells": {"start": "corners", "seed_corners": 1200},
}
"""SplatConfig fields of the library's SCR starts: the trained head (an early default), its analytic start (no
training, the fresh head's zero residuals) with or without the filled pixels, the textured-cell point start and the
triangulated-corner start (the library's default count, 800 per view as in its first runs, and 1200: about as many
seeds as SIFT's on herzjesu25). ``scr_corners_cells`` is the 1200-corner start with the ``cells`` start's points
added (corners_with_cells: a bench-only variant, measured and not shipped, bench/splat_init.md);
``scr_corners_gapcells`` adds the most textured of the cells in the corners' gaps (GAP_SPACINGS)."""
CORNER_CELLS = 12_000
"""Cells scr_corners_cells adds to the corners: the cells start's default count."""
GAP_SPACINGS = 4.0
"""scr_corners_gapcells: a cell is in a gap when it is farther than this many median corner spacings from every
corner."""


@contextlib.contextmanager
def corners_with_cells(n_cells: int, gaps_only: bool = False):
    """Within the block, the library's corners start also seeds the ``n_cells`` most textured trusted cells (the
    cells start's points) beside its triangulated corners; ``gaps_only``: chosen among the cells farther than
    GAP_SPACINGS median corner spacings from every corner."""
    import acesplat.splat.pipeline as pl
    from acesplat.splatcore.cell_seeds import cell_points, cell_texture, textured_cells

    corner_start, triangulated = pl._corner_start, pl.triangulated_points
    views_now: list = []

    def start(views, *args, **kwargs):
        views_now[:] = [views]
        return corner_start(views, *args, **kwargs)

    def union(keyframes, rgbs, n):
        pts, cols, per_view = triangulated(keyframes, rgbs, n)
        views = views_now[0]
        textures = [cell_texture(v.gray, v.validity.valid.shape) for v in views]
        valid = [v.validity.valid for v in views]
        if gaps_only:  # every valid cell farther than GAP_SPACINGS corner spacings from every corner may enter
            from scipy.spatial import cKDTree

            tree = cKDTree(pts)
            spacing = float(np.median(tree.query(pts, k=2)[0][:, 1]))
            gaps = []
            for v, m in zip(views, valid):
                d = tree.query(np.asarray(v.coords, np.float64).reshape(-1, 3), k=1)[0].reshape(m.shape)
                gaps.append(m & (d > GAP_SPACINGS * spacing))
            print(
                f"corner spacing {spacing:.4f}; valid cells {int(sum(m.sum() for m in valid))}, in gaps "
                f"{int(sum(g.sum() for g in gaps))}",
                flush=True,
            )
            valid = gaps
        masks = textured_cells(textures, valid, n_cells)
        parts = [cell_points(v.coords, m, v.rgb) for v, m in zip(views, masks)]
        cells = np.concatenate([p for p, _ in parts])
        colours = np.concatenate([c for _, c in parts])
        return np.concatenate([pts, cells]), np.concatenate([cols, colours]), per_view

    pl._corner_start, pl.triangulated_points = start, union
    try:
        yield
    finally:
        pl._corner_start, pl.triangulated_points = corner_start, triangulated


RANDOM_HALF_SIDE = 3.0
"""Random start: a cube of this many scene extents around the cameras (3DGS's random start is a fixed cube)."""
BUDGET_BOUND_ITERATIONS = 10**9
"""Iterations no start reaches in its budget: under --minutes alone the clock ends every start."""


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()
    except OSError:
        return "load average {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def get_map(name: str, scene: Path, given: str | None, out: Path, minutes: float, encoder: str | None) -> Path:
    if given:
        return Path(given)
    path = out / name / "map.pt"
    if path.is_file():
        return path
    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.mapfile import SceneMap, save_map
    from acesplat.scr.mapping import MappingConfig, default_short_side, map_scene

    train = read_split(scene, "train")
    enc, ident = load_encoder(encoder)
    side = default_short_side(train)
    t0 = time.monotonic()
    res = map_scene(train, enc, MappingConfig(minutes=minutes, short_side=side))
    save_map(path, SceneMap(res.head, ident, res.mean, side, {"scene": str(scene), "seconds": res.seconds}))
    print(f"  mapped {name} in {time.monotonic() - t0:.0f} s -> {path}")
    return path


class Curve:
    """eval_fn for optimise_gaussians: PSNR on a few views against the start's own clock (evaluations excluded)."""

    def __init__(self, start: float, train_views, test_views) -> None:
        self.start = start
        self.paused = 0.0
        self.train_views = train_views
        self.test_views = test_views
        self.points: list[dict] = []

    def clock(self) -> float:
        return time.monotonic() - self.start - self.paused

    def __call__(self, params, _train_seconds: float, iteration: int) -> None:
        t = self.clock()
        t_e = time.monotonic()
        g = gaussians_from_params(params)
        tr = evaluate_views(g, self.train_views)
        te = evaluate_views(g, self.test_views) if self.test_views else {"psnr": None}
        self.points.append(
            {
                "seconds": round(t, 2),
                "iteration": iteration,
                "train_psnr": tr["psnr"],
                "test_psnr": te["psnr"],
                "gaussians": len(g),
            }
        )
        self.paused += time.monotonic() - t_e


DENSE_STEP = OUTPUT_STRIDE // DENSE_OUTPUT_STRIDE
"""Cell (i, j) of the seeding grid sits on dense cell (2i, 2j): both grids put cell k at stride * k + 4 px."""


@torch.no_grad()
def remeasure_views(views: Sequence[SplatView], network: torch.nn.Module) -> dict:
    """Stage 2 seeds at depths re-measured between neighbouring training views (the same re-measurement as the pose
    alignment's keyframe depths, acesplat.align.keyframe_depth), for the scr_points start; through the init head it
    did not help, so it is not in the library (bench/splat_init.md).

    Replaces, in place, the SCR coordinates of each view's cells that its neighbours among ``views`` (the training
    views, exact poses) triangulate, by the triangulated point on the cell's ray, and recomputes the view's validity.
    Views need their SCR outputs (views.run_scr). Returns cells, cells re-measured, and the median relative depth
    change of those."""
    network.eval()
    images = [TrainingImage(v.gray, v.intrinsics, v.pose) for v in views]
    c2ws = np.stack([v.pose for v in views])
    cells = moved = 0
    changes: list[np.ndarray] = []
    for i, v in enumerate(views):
        h, w = v.coords.shape[:2]
        cells += h * w
        z = head_depth(network, images[i])
        known = z[z > 0]
        if not known.size:
            continue
        plain = [
            Keyframe(
                images[j].gray, images[j].intrinsics, images[j].c2w, np.zeros((1, 1), np.float32), DENSE_OUTPUT_STRIDE
            )
            for j in depth_neighbours(c2ws, i, float(np.median(known)))
        ]
        zr = refine_depth(Keyframe(images[i].gray, images[i].intrinsics, images[i].c2w, z, DENSE_OUTPUT_STRIDE), plain)
        zs, zh = np.zeros((h, w)), np.zeros((h, w))  # on the seeding grid, 0 past the dense grid's end
        sub_r, sub_h = zr[::DENSE_STEP, ::DENSE_STEP][:h, :w], z[::DENSE_STEP, ::DENSE_STEP][:h, :w]
        zs[: sub_r.shape[0], : sub_r.shape[1]], zh[: sub_h.shape[0], : sub_h.shape[1]] = sub_r, sub_h
        use = (zs != zh) & (zs > 0) & (zh > 0)
        moved += int(use.sum())
        if not use.any():
            continue
        changes.append(np.abs(zs[use] / zh[use] - 1.0))
        uv = cell_centers(h, w).reshape(h, w, 2)[use]
        coords = v.coords.copy()
        coords[use] = transform_points(v.pose, v.intrinsics.unproject(uv, zs[use])).astype(coords.dtype)
        v.coords = coords
        v.validity = cell_validity(coords, v.pose, v.intrinsics)
    return {
        "cells": cells,
        "remeasured_cells": moved,
        "median_depth_change": float(np.median(np.concatenate(changes))) if changes else 0.0,
    }


def run_method(method: str, scene: Path, map_path: Path, args, eval_train, eval_test, log) -> dict:
    frames = read_split(scene, "train").frames
    budget = args.minutes * 60.0
    # Same time: iterations the budget cannot reach, so the budget (a cap) ends every start. Same work: no cap.
    iterations = args.iterations if args.iterations else BUDGET_BOUND_ITERATIONS
    cap_minutes = None if args.iterations else args.minutes
    start = time.monotonic()
    curve = Curve(start, eval_train, eval_test)
    from acesplat.scr.mapfile import encoder_for_map, load_map

    m = load_map(map_path)
    info: dict = {}
    if method in SCR_VARIANTS:
        net = m.network(encoder_for_map(m, map_path, args.encoder))
        variant = (
            corners_with_cells(CORNER_CELLS, gaps_only=method == "scr_corners_gapcells")
            if method in ("scr_corners_cells", "scr_corners_gapcells")
            else contextlib.nullcontext()
        )
        with variant:
            res = splat_scene(
                frames,
                net,
                m.short_side,
                SplatConfig(
                    minutes=cap_minutes,
                    iterations=iterations,
                    seed=args.seed,
                    **SCR_VARIANTS[method],
                    **({"seed_cells": args.seed_cells} if method == "scr_cells" and args.seed_cells else {}),
                ),
                source=map_path,
                eval_fn=curve,
                eval_every_s=args.eval_every,
            )
        params, views, opt = res.params, res.train_views, res.optimize
        info = {
            k: res.stats.get(k)
            for k in (
                "start",
                "gaussians_initial",
                "stride",
                "valid_cell_fraction",
                "confirmed_cells",
                "prepare_seconds",
                "head_warmup_seconds",
            )
        }
    else:
        views = load_views(frames, m.short_side)
        poses = np.stack([v.pose for v in views])
        extent = scene_extent(poses, fallback=1.0)
        rng = np.random.default_rng(args.seed)
        if method.startswith("scr_points"):
            # The SCR coordinates as a point cloud with the same 3DGS point start as SIFT's: separates what the
            # points are worth from what the init head makes of them. scr_points re-measures them where neighbours
            # triangulate and keeps up to max_initial; scr_points_few keeps --points-cap of them at random;
            # scr_points_texture the --points-cap cells of most image gradient (where SIFT finds its points).
            net = m.network(encoder_for_map(m, map_path, args.encoder))
            run_scr(views, net, keep_features=False)
            if method == "scr_points":
                info["remeasured"] = remeasure_views(views, net)
            pts_l, cols_l, score_l = [], [], []
            for v in views:
                ok = v.validity.valid
                p, c = cell_points(v.coords, ok, v.rgb)  # each cell's coordinate, coloured by its own pixel
                pts_l.append(p)
                cols_l.append(c)
                score_l.append(cell_texture(v.gray, ok.shape)[ok])
            pts, cols, score = np.concatenate(pts_l), np.concatenate(cols_l), np.concatenate(score_l)
            cap = knob_default(SplatConfig, "max_initial") if method == "scr_points" else args.points_cap
            if len(pts) > cap:
                if method == "scr_points_texture":
                    keep = np.argsort(-score, kind="stable")[:cap]
                else:
                    keep = rng.choice(len(pts), cap, replace=False)
                pts, cols = pts[keep], cols[keep]
        elif method == "scr_corners":
            # Each training image's corners, triangulated with its neighbouring images by the keyframe alignment's
            # Lucas-Kanade (acesplat.align.keyframe_depth.triangulate_corners), as points: the SCR map gives the
            # keyframes' depth grid (their first guess and the plane the tracking warps by), the poses the rest.
            from acesplat.align.flow_pnp import KEYFRAME_ALIGN
            from acesplat.align.keyframe_align import keyframe_corners
            from acesplat.scr.keyframes import MapKeyframes

            net = m.network(encoder_for_map(m, map_path, args.encoder))
            kfs = MapKeyframes(read_split(scene, "train"), net, m.short_side)
            kfs.prepare_corners(KEYFRAME_ALIGN.corners)
            pts_l, cols_l = [], []
            for i, v in enumerate(views):
                c = keyframe_corners(kfs.keyframe(i), KEYFRAME_ALIGN.corners)
                if v.rgb.shape[:2] != kfs.images[i].gray.shape:
                    raise SystemExit(f"{scene}: view {i} is {v.rgb.shape[:2]}, its keyframe {kfs.images[i].gray.shape}")
                u = np.rint(c.uv).astype(np.int64)
                pts_l.append(c.X[c.triangulated])
                cols_l.append(v.rgb[u[c.triangulated, 1], u[c.triangulated, 0]])
            pts, cols = np.concatenate(pts_l), np.concatenate(cols_l)
            info["corners"] = int(len(pts))
        elif method == "sift":
            pts, cols = triangulated_points(
                [v.gray for v in views], [v.rgb for v in views], [v.intrinsics for v in views], list(poses)
            )
            if len(pts) < 2:
                raise SystemExit(f"{scene}: SIFT triangulation found {len(pts)} points")
        else:
            pts, cols = random_points(
                knob_default(SplatConfig, "max_initial"), poses[:, :3, 3], RANDOM_HALF_SIDE * extent, rng
            )
        g0 = gaussians_from_points(pts, cols)
        params = params_from_gaussians(g0)
        info.update(gaussians_initial=len(g0), prepare_seconds=curve.clock())
        remaining = None if cap_minutes is None else max(budget - curve.clock(), 1.0)
        cfg = OptimizeConfig(
            scene_extent=extent,
            max_gaussians=knob_default(SplatConfig, "max_gaussians"),
            iterations=iterations,
            seed=args.seed,
        )
        opt = optimise_gaussians(params, views, cfg, remaining, eval_fn=curve, eval_every_s=args.eval_every)
    seconds = curve.clock()
    curve(params, opt.seconds, opt.iterations)  # the final point of the curve
    g = gaussians_from_params(params)
    final_train = (
        views if args.final_train_views <= 0 else [views[i] for i in spread(len(views), args.final_train_views)]
    )
    tr = evaluate_views(g, final_train)
    test_views = load_views(read_split(scene, "test").frames, m.short_side)
    te = evaluate_views(g, test_views)
    out = {
        "method": method,
        "seconds": seconds,
        "iterations": opt.iterations,
        "skipped_steps": opt.skipped_steps,
        "gaussians_final": len(g),
        "train_psnr": tr["psnr"],
        "train_ssim": tr["ssim"],
        "train_views": tr["frames"],
        "test_psnr": te["psnr"],
        "test_ssim": te["ssim"],
        "test_views": te["frames"],
        "lifecycle": opt.events,
        "curve": curve.points,
        **info,
    }
    log(
        f"  {method:6s} {out['train_psnr']:6.2f} / {out['test_psnr']:6.2f} dB  SSIM {out['train_ssim']:.3f} / "
        f"{out['test_ssim']:.3f}  {out['gaussians_initial']:>7d} -> {len(g):>7d} Gaussians  {opt.iterations} it  "
        f"{seconds:.0f} s"
    )
    return out


def plot(results: dict, path: Path, minutes: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(results)
    fig, axes = plt.subplots(1, len(scenes), figsize=(6 * len(scenes), 4.5), squeeze=False)
    colours = {
        "scr": "tab:red",
        "scr_analytic": "tab:orange",
        "scr_analytic_fill": "tab:pink",
        "scr_cells": "tab:brown",
        "scr_points": "tab:green",
        "scr_points_few": "tab:olive",
        "scr_points_texture": "tab:cyan",
        "sift": "tab:blue",
        "scr_corners": "tab:red",
        "random": "tab:gray",
    }
    for ax, name in zip(axes[0], scenes):
        for r in results[name]:
            pts = r["curve"]
            t = [p["seconds"] / 60 for p in pts]
            ax.plot(
                t,
                [p["train_psnr"] for p in pts],
                "-",
                color=colours.get(r["method"], "black"),
                label=f"{r['method']} train",
            )
            if pts and pts[0]["test_psnr"] is not None:
                ax.plot(
                    t,
                    [p["test_psnr"] for p in pts],
                    "--",
                    color=colours.get(r["method"], "black"),
                    label=f"{r['method']} test",
                )
        ax.set_xlim(0, minutes)
        ax.set_xlabel("wall-clock minutes (Stage 2, this start's preparation included)")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="Stage 2 budget per start")
    ap.add_argument("--iterations", type=int, default=0, help="the same iterations per start instead of the budget")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "bench_splat")
    ap.add_argument("--scenes", default="builtin,herzjesu")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--builtin-map")
    ap.add_argument("--herzjesu-map")
    ap.add_argument("--map", help="map of a scene given by path in --scenes")
    ap.add_argument("--herzjesu", type=Path, default=HERZJESU)
    ap.add_argument("--encoder", help="encoder weights for maps made here / not where a map says")
    ap.add_argument("--map-minutes", type=float, default=4.0)
    ap.add_argument("--eval-every", type=float, default=30.0, help="seconds of training between curve points")
    ap.add_argument("--eval-views", type=int, default=6, help="train and test views per curve point")
    ap.add_argument("--final-train-views", type=int, default=0, help="0: score every training view at the end")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--points-cap", type=int, default=12_000, help="points of scr_points_few / scr_points_texture")
    ap.add_argument("--seed-cells", type=int, default=0, help="scr_cells: SplatConfig.seed_cells (0: its default)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    lines: list[str] = []

    def log(s: str) -> None:
        print(s, flush=True)
        lines.append(s)

    log(f"machine: {machine_line()}")
    log(f"uptime at start: {uptime()}")
    per_start = f"{args.iterations} iterations" if args.iterations else f"budget {args.minutes:g} min"
    log(f"{per_start} per start; torch threads {args.threads}")
    results: dict = {}
    previous = args.out / "bench_splat_init.json"
    if previous.is_file():  # keep earlier runs' results for the (scene, start) pairs not run again
        results = json.loads(previous.read_text()).get("results", {})
    for name in args.scenes.split(","):
        if name == "builtin":
            scene = args.out / "builtin"
            if not (scene / "train").is_dir():
                from acesplat.synth import synthesize

                synthesize(scene, seed=0, overwrite=True)
        elif name == "herzjesu":
            scene = args.herzjesu
        else:
            scene = Path(name)
        given = {"builtin": args.builtin_map, "herzjesu": args.herzjesu_map}.get(name, args.map)
        map_path = get_map(Path(name).name, scene, given, args.out, args.map_minutes, args.encoder)
        from acesplat.scr.mapfile import load_map

        side = load_map(map_path).short_side
        tr_frames = read_split(scene, "train").frames
        te_frames = read_split(scene, "test").frames
        eval_train = load_views([tr_frames[i] for i in spread(len(tr_frames), args.eval_views)], side)
        eval_test = load_views([te_frames[i] for i in spread(len(te_frames), args.eval_views)], side)
        log(f"{name}: {scene} ({len(tr_frames)} train / {len(te_frames)} test, short side {side}), map {map_path}")
        log("  start  train / test PSNR     SSIM train / test   Gaussians start -> end   iterations   seconds")
        methods = args.methods.split(",")
        results[name] = [r for r in results.get(name, []) if r["method"] not in methods]
        for method in methods:
            results[name].append(run_method(method, scene, map_path, args, eval_train, eval_test, log))
            results[name].sort(key=lambda r: METHODS.index(r["method"]) if r["method"] in METHODS else len(METHODS))
            write_json(
                args.out / "bench_splat_init.json",
                {
                    "machine": machine_line(),
                    "args": {k: str(v) for k, v in vars(args).items()},
                    "results": results,
                    "log": lines,
                },
            )
    log(f"uptime at end: {uptime()}")
    plot(results, args.out / "bench_splat_init.png", args.minutes)
    write_json(
        args.out / "bench_splat_init.json",
        {
            "machine": machine_line(),
            "args": {k: str(v) for k, v in vars(args).items()},
            "results": results,
            "log": lines,
        },
    )
    print(f"-> {args.out / 'bench_splat_init.json'}, {args.out / 'bench_splat_init.png'}")


if __name__ == "__main__":
    main()
