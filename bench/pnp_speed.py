"""PnP alone on recorded scene-coordinate grids: milliseconds per stage, old vs new solver, poses compared.

    record: PYTHONPATH=. python bench/pnp_speed.py record --synth 24 --out DIR          # synthetic facade grids
            PYTHONPATH=. python bench/pnp_speed.py record --npz RAW.npz --name NAME --out DIR   # gate_foreign collect
            PYTHONPATH=. python bench/pnp_speed.py record --map MAP --scene SCENE --name NAME --out DIR
    run:    PYTHONPATH=. python bench/pnp_speed.py run DIR/NAME [DIR/NAME2 ...] [--repeats 3]

A recorded set is NAME.coords.npy (F, h, w, 3) float32, NAME.K.npy (F, 6) (fx, fy, cx, cy, width, height of the
network input), NAME.kinds.npy (F,) ('true' or a bad kind) and, when known, NAME.gt.npy (F, 4, 4) camera-to-world.
``run`` solves every grid with each configuration (the edge's PnPSettings: ransac_ap3p, 256 iterations; the same
with batch_p3p; batch_p3p given a prior 2 cm / 0.5 deg off the frame's own pose), times RANSAC, the robust
refinement, the fallback and the gate, and compares the new poses, inlier counts and gate verdicts with the old.
Results: bench/pnp_speed.md.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import acesplat.core.pnp as pnp_mod
from acesplat.core.camera import Intrinsics
from acesplat.core.gate import gate_result
from acesplat.core.geometry import look_at, pose_error, rodrigues_to_matrix
from acesplat.core.grid import cell_centers
from acesplat.core.pnp import PnPConfig, solve_from_grid

CLOCK = time.perf_counter
"""Wall clock; ``run --clock cpu`` uses this process's CPU time instead (close to an idle machine's wall time when
other jobs share the cores, with single-threaded BLAS: OPENBLAS_NUM_THREADS=1)."""
EDGE = PnPConfig(method="ransac_ap3p", iterations=256)
"""The edge's PnPSettings as a PnPConfig (edge/runtime.py)."""
CONFIGS = {"old": EDGE}
try:
    CONFIGS["new"] = replace(EDGE, method="batch_p3p")
except ValueError:  # the tree before batch_p3p (for the "before" rows)
    pass


def isa() -> str:
    """The vector extensions that matter here, from /proc/cpuinfo (as lscpu | grep -o -E ... | sort -u)."""
    try:
        flags = set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        return "unknown"
    return " ".join(f for f in ("avx2", "avx512f", "avx512_bf16", "avx512_vnni", "amx_bf16") if f in flags)


def synth_grids(n: int, seed: int = 0) -> dict:
    """``n`` facade grids (45, 68, 3) of a 540x360 input: a wall with relief 5-12 m away, pixel-sized noise with
    a tail, 30-60% gross outliers."""
    rng = np.random.default_rng(seed)
    intr = Intrinsics(485.0, 485.0, 270.0, 180.0, 540, 360)
    h, w = 45, 68
    pix = cell_centers(h, w)
    coords, gts, Ks, kinds = [], [], [], []
    for _ in range(n):
        eye = np.array([rng.uniform(-3, 3), rng.uniform(-12, -5), rng.uniform(1, 3)])
        target = np.array([rng.uniform(-2, 2), 0.0, rng.uniform(1, 4)])
        T = look_at(eye, target)  # camera-to-world; the facade is the plane y = relief(x, z)
        rays = intr.unproject(pix, np.ones(len(pix)))  # camera rays with z = 1
        d = rays @ T[:3, :3].T
        depth = -eye[1] / d[:, 1]
        X = eye + depth[:, None] * d
        depth *= 1.0 + 0.04 * np.sin(X[:, 0] * 1.3) * np.cos(X[:, 2] * 0.9)  # relief, along the rays
        X = eye + depth[:, None] * d
        z = (X - T[:3, 3]) @ T[:3, 2]
        sigma = np.where(rng.random(len(X)) < 0.8, 1.5, 4.0) * z / intr.fx  # pixels at the point's depth
        X += rng.normal(0.0, 1.0, X.shape) * sigma[:, None]
        bad = rng.random(len(X)) < rng.uniform(0.3, 0.6)
        X[bad] += rng.normal(0.0, 1.0, (int(bad.sum()), 3))
        coords.append(X.reshape(h, w, 3).astype(np.float32))
        gts.append(T)
        Ks.append([intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height])
        kinds.append("true")
    return {"coords": np.stack(coords), "K": np.array(Ks), "kinds": np.array(kinds), "gt": np.stack(gts)}


def record(args: argparse.Namespace) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.synth:
        sets = {args.name or "synth": synth_grids(args.synth)}
    elif args.npz:
        raw = np.load(args.npz)
        d = {k: raw[k] for k in ("coords", "K", "kinds")}
        if "gt" in raw:  # the true frames' poses, in the order they were collected (bench/gate_foreign.py)
            gt = np.full((len(d["kinds"]), 4, 4), np.nan)
            gt[d["kinds"] == "true"] = raw["gt"]
            d["gt"] = gt
        sets = {args.name: d}
    else:
        sets = {args.name: map_grids(args.map, args.scene)}
    for name, d in sets.items():
        for k, v in d.items():
            np.save(out / f"{name}.{k}.npy", v)
        print(f"wrote {out / name}.*.npy: {len(d['coords'])} grids {d['coords'].shape[1:]}")


def map_grids(map_path: str, scene: str) -> dict:
    """A Stage 1 map's grids for a scene's test split (the network runs once, here)."""
    import torch

    from acesplat.core.scene import read_split
    from acesplat.scr.localize import Localizer
    from acesplat.scr.mapfile import encoder_for_map, load_map

    torch.set_num_threads(1)
    m = load_map(map_path)
    loc = Localizer(m.network(encoder_for_map(m, map_path)), m.short_side, {})
    coords, Ks, gts = [], [], []
    for f in read_split(scene, "test").frames:
        c, ni = loc.predict(f.load_rgb(), f.intrinsics)
        coords.append(c.astype(np.float32))
        Ks.append([ni.fx, ni.fy, ni.cx, ni.cy, ni.width, ni.height])
        gts.append(f.pose)
    return {
        "coords": np.stack(coords),
        "K": np.array(Ks),
        "kinds": np.array(["true"] * len(coords)),
        "gt": np.stack(gts),
    }


class StageClock:
    """Times the solver's stages by wrapping its module-level functions (RANSAC + refinement per solver call)."""

    def __init__(self) -> None:
        self.calls: list[float] = []
        self.refine: list[float] = []
        self._solve = pnp_mod._ransac_and_refine
        self._refine = pnp_mod.refine_pose_robust

    def __enter__(self) -> StageClock:
        def solve(*a, **kw):
            t = CLOCK()
            r = self._solve(*a, **kw)
            self.calls.append((CLOCK() - t) * 1e3)
            return r

        def refine(*a, **kw):
            t = CLOCK()
            r = self._refine(*a, **kw)
            self.refine.append((CLOCK() - t) * 1e3)
            return r

        pnp_mod._ransac_and_refine, pnp_mod.refine_pose_robust = solve, refine
        return self

    def __exit__(self, *exc) -> None:
        pnp_mod._ransac_and_refine, pnp_mod.refine_pose_robust = self._solve, self._refine


def solve_timed(c: np.ndarray, intr: Intrinsics, cfg: PnPConfig, prior: np.ndarray | None = None) -> tuple:
    with StageClock() as clk:
        t0 = CLOCK()
        res = solve_from_grid(c, intr, config=cfg, **({"prior_c2w": prior} if prior is not None else {}))
        t1 = CLOCK()
        res = gate_result(res, c, intr, cfg)
        t2 = CLOCK()
    first = clk.calls[0] if clk.calls else 0.0
    ref_first = clk.refine[0] if clk.calls and clk.refine else 0.0
    stages = {
        "ransac": first - ref_first if clk.calls else 0.0,
        "refine": ref_first if clk.calls else sum(clk.refine),
        "fallback": sum(clk.calls[1:]),
        "solve": (t1 - t0) * 1e3,
        "gate": (t2 - t1) * 1e3,
        "total": (t2 - t0) * 1e3,
    }
    return res, stages


def perturb(T: np.ndarray, rng: np.random.Generator, cm: float = 2.0, deg: float = 0.5) -> np.ndarray:
    """``T`` moved by ``cm`` centimetres and turned by ``deg`` degrees in random directions."""
    d = np.eye(4)
    a = rng.normal(size=3)
    d[:3, :3] = rodrigues_to_matrix(a / np.linalg.norm(a) * np.deg2rad(deg))
    b = rng.normal(size=3)
    d[:3, 3] = b / np.linalg.norm(b) * cm / 100.0
    return T @ d


def table_row(label: str, per_frame: list[list[dict]]) -> str:
    """One markdown row: each stage's p50 over every solve and, in brackets, over each frame's fastest repeat."""
    flat = [s for runs in per_frame for s in runs]
    fastest = [min(runs, key=lambda s: s["total"]) for runs in per_frame]
    cell = {}
    for k in flat[0]:
        v = np.array([s[k] for s in flat])
        f = np.array([s[k] for s in fastest])
        cell[k] = f"{np.percentile(v, 50):.1f} ({np.percentile(f, 50):.1f})"
    p90 = np.percentile([s["total"] for s in flat], 90)
    p90f = np.percentile([s["total"] for s in fastest], 90)
    return (
        f"| {label} | {len(per_frame)} | {cell['ransac']} | {cell['refine']} | {cell['fallback']} | "
        f"{cell['gate']} | {cell['total']} | {p90:.1f} ({p90f:.1f}) |"
    )


def run(args: argparse.Namespace) -> None:
    global CLOCK
    CLOCK = time.process_time if args.clock == "cpu" else time.perf_counter
    load = os.getloadavg()
    rows = {}
    for base in args.sets:
        coords = np.load(f"{base}.coords.npy")
        Ks = np.load(f"{base}.K.npy")
        kinds = np.load(f"{base}.kinds.npy")
        gt = np.load(f"{base}.gt.npy") if Path(f"{base}.gt.npy").exists() else None
        name = Path(base).name
        st: dict[str, dict[int, list[dict]]] = {k: {} for k in ("old", "new", "prior", "prior_wrong")}
        configs = {k: v for k, v in CONFIGS.items() if k in args.configs}
        cmp = []
        rng = np.random.default_rng(0)
        for i, (c, k, kind) in enumerate(zip(coords, Ks, kinds)):
            c = c.astype(np.float64)
            intr = Intrinsics(k[0], k[1], k[2], k[3], int(k[4]), int(k[5]))
            out = {}
            for label, cfg in configs.items():
                runs = [solve_timed(c, intr, cfg) for _ in range(args.repeats)]
                st[label][i] = [s for _, s in runs]
                out[label] = runs[0][0]
            if "new" not in out:  # the tree before batch_p3p: the old solver alone
                out["new"] = out["old"]
            if "old" not in out:  # the new solver alone: its poses stand in for the comparison
                out["old"] = out["new"]
            a, b = out["old"], out["new"]
            row = {"i": i, "kind": str(kind), "old_inl": a.inliers, "new_inl": b.inliers}
            row.update(old_loc=a.localized, new_loc=b.localized, old_score=a.gate.score, new_score=b.gate.score)
            if a.T_c2w is not None and b.T_c2w is not None:
                dt, dr = pose_error(b.T_c2w, a.T_c2w)
                row.update(d_mm=dt * 1e3, d_mdeg=dr * 1e3)
            if gt is not None and np.isfinite(gt[i]).all():
                for label, r in (("old", a), ("new", b)):
                    e = pose_error(r.T_c2w, gt[i]) if r.T_c2w is not None else (np.inf, np.inf)
                    row[f"{label}_err_cm"], row[f"{label}_err_deg"] = e[0] * 100, e[1]
            if kind == "true" and a.localized and "new" in configs and "old" in configs:
                prior = perturb(a.T_c2w, rng)
                runs = [solve_timed(c, intr, CONFIGS["new"], prior) for _ in range(args.repeats)]
                st["prior"][i] = [s for _, s in runs]
                pr = runs[0][0]
                dt, dr = pose_error(pr.T_c2w, a.T_c2w)
                row.update(prior_mm=dt * 1e3, prior_mdeg=dr * 1e3, prior_inl=pr.inliers)
                wrong = perturb(a.T_c2w, rng, cm=300.0, deg=30.0)
                runs = [solve_timed(c, intr, CONFIGS["new"], wrong) for _ in range(args.repeats)]
                st["prior_wrong"][i] = [s for _, s in runs]
                wr = runs[0][0]
                dt, dr = pose_error(wr.T_c2w, b.T_c2w)
                row.update(wrong_prior_mm=dt * 1e3, wrong_prior_inl=wr.inliers)
            cmp.append(row)
            if args.verbose:
                print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()}))
        rows[name] = {"frames": cmp, "ms": {k: {str(j): v for j, v in d.items()} for k, d in st.items()}}
        print(f"\n## {name}: {len(coords)} grids {coords.shape[1]}x{coords.shape[2]}, repeats {args.repeats}")
        for group in ("true", "bad"):
            sel = [j for j, r in enumerate(cmp) if (r["kind"] == "true") == (group == "true")]
            if not sel:
                continue
            print(f"{group} frames: ms p50 over every solve (p50 of each frame's fastest repeat, the least loaded)")
            print("| config | frames | ransac | refine | fallback | gate | total p50 | total p90 |")
            print("|---|---|---|---|---|---|---|---|")
            for label, per_frame in st.items():
                runs_of = [per_frame[j] for j in sel if j in per_frame]
                if runs_of:
                    print(table_row(label, runs_of))
        true = [r for r in cmp if r["kind"] == "true"]
        bad = [r for r in cmp if r["kind"] != "true"]
        both = [r for r in true if r["old_loc"] and r["new_loc"] and "d_mm" in r]
        if both:
            d = np.array([[r["d_mm"], r["d_mdeg"]] for r in both])
            print(
                f"true frames localized by both: {len(both)}; new vs old: median {np.median(d[:, 0]):.3f} mm / "
                f"{np.median(d[:, 1]):.3f} mdeg, max {d[:, 0].max():.3f} mm / {d[:, 1].max():.3f} mdeg; "
                f"inliers new - old median {np.median([r['new_inl'] - r['old_inl'] for r in both]):.0f}"
            )
        print(
            f"TRACKING true: old {sum(r['old_loc'] for r in true)}/{len(true)}, new {sum(r['new_loc'] for r in true)}; "
            f"bad frames TRACKING: old {sum(r['old_loc'] for r in bad)}, new {sum(r['new_loc'] for r in bad)} of "
            f"{len(bad)}; largest bad score: old {max((r['old_score'] for r in bad), default=0):.3f}, "
            f"new {max((r['new_score'] for r in bad), default=0):.3f}"
        )
        if gt is not None:
            for label in ("old", "new"):
                e = np.array([[r[f"{label}_err_cm"], r[f"{label}_err_deg"]] for r in true if f"{label}_err_cm" in r])
                print(f"{label} vs ground truth: median {np.median(e[:, 0]):.2f} cm / {np.median(e[:, 1]):.3f} deg")
        pri = [r for r in true if "prior_mm" in r]
        if pri:
            d = np.array([[r["prior_mm"], r["prior_mdeg"]] for r in pri])
            print(
                f"prior 2 cm / 0.5 deg off: {len(pri)} frames, vs old pose median {np.median(d[:, 0]):.3f} mm / "
                f"{np.median(d[:, 1]):.3f} mdeg, max {d[:, 0].max():.3f} mm; wrong prior (3 m / 30 deg): vs new "
                f"pose max {max(r['wrong_prior_mm'] for r in pri):.3f} mm"
            )
    print(f"\nclock {args.clock}; load average before {load[0]:.1f}, after {os.getloadavg()[0]:.1f}; ISA {isa()}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("--out", required=True)
    r.add_argument("--name", default=None)
    r.add_argument("--synth", type=int, default=0)
    r.add_argument("--npz", default=None)
    r.add_argument("--map", default=None)
    r.add_argument("--scene", default=None)
    r.set_defaults(fn=record)
    u = sub.add_parser("run")
    u.add_argument("sets", nargs="+")
    u.add_argument("--repeats", type=int, default=3)
    u.add_argument("--json", default=None)
    u.add_argument("--verbose", action="store_true")
    u.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    u.add_argument("--configs", nargs="+", default=list(CONFIGS), help="old (the edge's solver), new (batch_p3p)")
    u.set_defaults(fn=run)
    args = ap.parse_args()
    args.fn(args)


if __name__ == "__main__":
    main()
