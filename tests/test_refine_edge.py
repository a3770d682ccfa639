"""Refinement in the edge runtime: replay --refine numbers, bundles with and without Gaussian models, the worker
thread, export --splat."""

from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.apps.edge_cli import app
from acesplat.core.gaussians import Gaussians, concat_gaussians
from acesplat.core.ply import read_ply, write_ply
from acesplat.core.scene import read_split
from edge.refine.deadline import CostEstimate
from edge.refine.keyframes import KeyframePolicy, KeyframeSelector
from edge.refine.refiner import BatchReport
from edge.refine.worker import Candidate, RefineWorker
from tests.refine_scene import depth_gaussians


@pytest.fixture(scope="module")
def bundle_with_gaussians(tiny, tmp_path_factory) -> Path:
    """The tiny bundle plus Gaussians from three training views' depth, moved and recoloured at random."""
    from export.splat_export import add_gaussians

    root = tmp_path_factory.mktemp("refine_bundle")
    b = root / "bundle"
    shutil.copytree(tiny["bundle"], b)
    frames = read_split(tiny["scene"], "train").frames
    rng = np.random.default_rng(0)
    g = concat_gaussians([depth_gaussians(f, 3, rng, 0.02, 0.15) for f in frames[:6:2]])
    write_ply(root / "start.ply", g)
    add_gaussians(b, root / "start.ply")
    return b


def test_replay_refine_reports_psnr_gain_and_saves_the_map(tiny, bundle_with_gaussians, tmp_path) -> None:
    """A generous budget, so the quality check does not depend on how busy the machine is (the deadline
    itself is tested with a fake clock in test_refine_batches)."""
    out, saved = tmp_path / "r.json", tmp_path / "refined.ply"
    r = CliRunner().invoke(
        app,
        [
            "replay",
            str(bundle_with_gaussians),
            str(tiny["scene"]),
            "--split",
            "train",
            "--refine",
            "--budget-ms",
            "2000",
            "--threads",
            "1",
            "--json",
            str(out),
            "--save-splat",
            str(saved),
        ],
    )
    assert r.exit_code == 0, r.output
    s = json.loads(out.read_text())
    assert s["localized"] == s["frames"] == 12
    ref = s["refine"]
    for k in ("psnr_before", "psnr_after", "keyframes", "gaussians_added", "gaussians_final", "steps", "timing_ms"):
        assert k in ref
    for k in ("window", "candidate_wall", "batch", "step", "render", "guard"):
        assert set(ref["timing_ms"][k]) == {"mean", "p50", "p90", "p95", "p99", "max"}
    assert "refine" in s["timing_ms"]  # beside the localization stages
    assert ref["keyframes"] == 12 and ref["keyframes_committed"] >= 6  # measured 9 of 12
    assert ref["steps"] >= 150  # measured 300
    assert ref["psnr_after"] > ref["psnr_before"] + 8.0  # measured 10.9 -> 22.3 dB
    assert ref["gaussians_final"] == ref["gaussians_initial"] + ref["gaussians_added"] - ref["gaussians_pruned"] - ref[
        "gaussians_capped"
    ] + ref["witness"].get("revived", 0) - ref["witness"].get("added_removed", 0)
    assert ref["errors"] == []
    assert ref["witness"]["witnesses"] == ref["witness"]["offered"] == 12 and not ref["failed"]
    assert len(read_ply(saved)) == ref["gaussians_final"] and ref["save"]["failures"] == 0
    assert "refine: PSNR" in r.output and "refine: checking 12 witness views" in r.output


def test_refine_on_a_bundle_without_gaussians_says_so_and_localizes(tiny, tmp_path) -> None:
    out = tmp_path / "r.json"
    r = CliRunner().invoke(
        app, ["replay", str(tiny["bundle"]), str(tiny["scene"]), "--refine", "--threads", "1", "--json", str(out)]
    )
    assert r.exit_code == 0, r.output
    assert "no Gaussian model" in r.output
    s = json.loads(out.read_text())
    assert s["localized"] == s["frames"] and "refine" not in s


def test_refine_refuses_a_tampered_gaussians_file(bundle_with_gaussians, tiny, tmp_path) -> None:
    b = tmp_path / "b"
    shutil.copytree(bundle_with_gaussians, b)
    with open(b / "gaussians.ply", "r+b") as f:
        f.seek(-8, 2)
        f.write(b"\x01" * 8)
    r = CliRunner().invoke(app, ["replay", str(b), str(tiny["scene"]), "--refine", "--threads", "1"])
    assert r.exit_code == 2
    assert "gaussians.ply" in r.output and "sha256" in r.output


class _StepRefiner:
    """Stands in for Refiner: a batch asks for one 1 ms step after another until told no."""

    def __init__(self) -> None:
        self.map = Gaussians.zeros(0, 0)
        self.started = threading.Event()
        self.names: list[str] = []
        self.totals = {"no_time": 0}

    def batch(self, kf, rep: BatchReport):
        self.names.append(kf.name)
        self.started.set()
        step = CostEstimate(0.001, name="step")
        while (yield ("step", step, 0.0)):
            time.sleep(0.001)
        rep.outcome = "committed"

    def abandon(self, gen, rep: BatchReport) -> BatchReport:
        gen.close()
        rep.outcome = "no_time"
        return rep


def _candidate(name: str, seconds: float, moved: float) -> Candidate:
    pose = np.eye(4)
    pose[0, 3] = moved
    return Candidate(
        pose, 500, True, time.perf_counter() + seconds, lambda: type("K", (), {"name": name})(), None, name
    )


def _run_preempted(max_windows: int) -> tuple[_StepRefiner, RefineWorker]:
    """Keyframe 'a' runs; 'b', 'c', 'd' arrive meanwhile (only 'd' survives); then two preemptions."""
    ref = _StepRefiner()
    w = RefineWorker(
        ref,
        KeyframeSelector(KeyframePolicy(min_inliers=0, min_translation_m=0.0)),
        max_windows=max_windows,
        step_windows=2,
    )
    try:
        w.submit(_candidate("a", 30.0, 0.0))
        assert ref.started.wait(5.0)
        for i, name in enumerate(("b", "c", "d")):
            w.submit(_candidate(name, 30.0, 1.0 + i))
        for _ in range(2):  # the next frames' localizations start: the running batch stops at its next step
            time.sleep(0.05)
            w.preempt()
        time.sleep(0.05)
        w.wait_idle(0.5)
    finally:
        w.close()
    assert w.dropped == 2 and w.stats.candidates == 4
    return ref, w


def test_worker_latest_wins_and_a_preempted_batch_ends_in_one_window() -> None:
    ref, w = _run_preempted(max_windows=1)
    assert ref.names == ["a", "d"]  # 'a' stopped stepping at the preemption; 'd' was the newest frame
    assert [r.outcome for r in w.stats.reports][:1] == ["committed"]


def test_worker_carries_a_preempted_batch_into_the_next_frame_window() -> None:
    ref, w = _run_preempted(max_windows=4)
    assert ref.names == ["a"]  # 'd' lent 'a' its time window instead of becoming a keyframe
    assert w.stats.absorbed == 1
    # Steps wait for at most two windows: at the second preemption the batch ends its optimisation and completes.
    assert [(r.outcome, r.windows) for r in w.stats.reports] == [("committed", 2)]


def test_worker_skips_a_frame_whose_deadline_passed() -> None:
    ref = _StepRefiner()
    w = RefineWorker(ref, KeyframeSelector(KeyframePolicy(min_inliers=0)))
    try:
        w.submit(_candidate("late", -0.01, 0.0))
        assert w.wait_idle(5.0)
    finally:
        w.close()
    assert ref.names == [] and w.stats.late == 1


@pytest.fixture(scope="module")
def splat_bundle(tiny, tmp_path_factory) -> Path:
    """`acesplat splat` (a few iterations, the init head trained) and export --splat on the tiny room."""
    from acesplat.apps.cli import app as desktop

    root = tmp_path_factory.mktemp("splat_export")
    r = CliRunner().invoke(
        desktop,
        [
            "splat",
            str(tiny["scene"]),
            "--map",
            str(tiny["map"]),
            "-o",
            str(root / "splat"),
            "--iterations",
            "5",
            "--max-gaussians",
            "4000",
            "--start",
            "head",
            "--head-warmup",
            "0.08",
            "--joint-head",
        ],
    )
    assert r.exit_code == 0, r.output
    trained = json.loads((root / "splat" / "splat.json").read_text())
    assert trained["head_warmup_steps"] == 1 and trained["head_steps"] >= 1  # 5 // 5 warm-up steps, then jointly
    b = root / "bundle"
    shutil.copytree(tiny["bundle"], b)
    from export.splat_export import export_splat

    export_splat(b, root / "splat", tiny["map"])
    return b


def test_export_splat_lists_models_checked_against_torch(splat_bundle) -> None:
    from acesplat.core.bundle import load_bundle
    from acesplat.splatcore.bundle_section import ROLE_GAUSSIANS, ROLE_SPLAT_INIT
    from edge.refine.bundle_models import bundle_gaussians
    from export.splat_export import ROLE_GAUSSIANS as EXPORT_GAUSSIANS
    from export.splat_export import ROLE_SPLAT_INIT as EXPORT_INIT

    assert (ROLE_GAUSSIANS, ROLE_SPLAT_INIT) == (EXPORT_GAUSSIANS, EXPORT_INIT)
    b = load_bundle(splat_bundle)  # verifies every listed file's size and sha256
    assert b.has(ROLE_GAUSSIANS) and b.has(ROLE_SPLAT_INIT) and b.has("scr_fp32")
    checks = b.manifest["checks"]
    parity = checks["splat_init_fp32_vs_torch"]
    assert parity["max_abs_diff"] < 1e-4 * max(1.0, parity["max_abs_output"])
    assert parity["max_abs_output"] > 0 and not parity["untrained_head"]  # a trained head is its own check
    assert "splat_init_probe_fp32_vs_torch" not in checks
    # What the edge runs: the SCR graph's features output into the initializer, against torch end to end.
    via = checks["splat_init_via_scr_fp32_vs_torch"]
    assert via["max_abs_diff"] < 1e-4 * max(1.0, via["max_abs_output"])
    int8 = checks["splat_init_via_scr_int8_vs_torch"]  # INT8 features: close, not equal
    assert 0.0 < int8["max_abs_diff"] < 0.2 * max(1e-3, int8["max_abs_output"])  # measured 0.11 of the output
    assert b.format_version == 2
    assert b.manifest["splat"]["init"]["inputs"]["features"] == b.scr["features"]["shape"] == [1, 32, 8, 10]
    assert len(bundle_gaussians(b)) == b.manifest["splat"]["gaussians"]


def test_onnx_seeder_places_gaussians_on_scr_rays(splat_bundle, tiny) -> None:
    from acesplat.core.bundle import load_bundle
    from acesplat.core.preprocess import to_gray_input
    from acesplat.splatcore.pixel_coords import pixel_depths
    from edge.inference import ScrSession
    from edge.refine.onnx_seeder import onnx_seeder_for
    from edge.refine.refiner import Keyframe
    from tests.refine_scene import true_cells

    b = load_bundle(splat_bundle)
    seeder = onnx_seeder_for(b)
    f = read_split(tiny["scene"], "train").frames[3]
    gray, k_in = to_gray_input(f.load_rgb(), f.intrinsics, b.input_size)
    _, feats = ScrSession(b.scr_model("fp32"), b.input_size, threads=1).run_with_features(gray)
    assert feats.shape == seeder.features_shape == (32, 8, 10)
    kf = Keyframe(f.pose, f.load_rgb().astype(np.float32) / 255, f.intrinsics, true_cells(f), k_in, f.name, feats)
    g = seeder(kf, np.ones((f.intrinsics.height, f.intrinsics.width), bool), 300, 3, np.random.default_rng(0))
    assert 150 <= len(g) <= 300 and g.sh_degree == 3  # measured 192
    assert np.allclose(g.opacities(), 0.8, atol=0.01)  # the prior opacity, residuals small (measured within 1e-4)
    pix = pixel_depths(kf.coords, f.pose, k_in, f.intrinsics)
    d = np.linalg.norm(pix.centres.reshape(-1, 3)[None] - g.means[:, None], axis=2).min(axis=1)
    assert d.max() < 1e-4  # every centre is a pixel's SCR point
    # Zero residuals decode to the analytic start: the pixel's colour, the prior opacity, identity rotation.
    z = seeder.decode(
        np.zeros((1, seeder.channels)), np.array([[0.2, 0.4, 0.6]]), np.zeros((1, 3)), np.array([2.0]), 100.0, 2.0, 3
    )
    assert np.allclose(g.sh.shape[1:], (16, 3))
    assert np.allclose(z.sh[0, 0] * 0.28209479177387814 + 0.5, [0.2, 0.4, 0.6], atol=1e-6)
    assert np.allclose(z.opacities(), 0.8, atol=1e-6) and np.allclose(z.quats, [[1, 0, 0, 0]])
    assert np.allclose(np.exp(z.log_scales), 0.7 * 2.0 * 2.0 / 100.0)


def test_bad_refine_inputs_give_one_line_errors(bundle_with_gaussians, tiny, tmp_path) -> None:
    r = CliRunner().invoke(
        app, ["replay", str(bundle_with_gaussians), str(tiny["scene"]), "--refine", "--budget-ms", "0"]
    )
    assert r.exit_code == 2 and "--budget-ms must be positive" in r.output
    from acesplat.core.errors import InputError
    from export.splat_export import add_gaussians, export_splat

    b = tmp_path / "b"
    shutil.copytree(tiny["bundle"], b)
    with pytest.raises(InputError, match="splat folder does not exist"):
        export_splat(b, tmp_path / "no_such_splat", tiny["map"])
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(InputError, match="bad.ply"):
        add_gaussians(b, tmp_path / "bad.ply")


def test_replay_refine_seeds_through_the_initializer_with_the_localizer_features(splat_bundle, tiny, tmp_path) -> None:
    """The map keeps one Gaussian in ten, so every keyframe has holes to seed: whether the splat itself leaves any
    depends on its fit (the full tiny splat covered every test view once its depth warp read the right cells)."""
    from acesplat.core.bundle import load_bundle
    from edge.refine.bundle_models import bundle_gaussians
    from export.splat_export import add_gaussians

    sparse = tmp_path / "sparse"
    shutil.copytree(splat_bundle, sparse)
    g = bundle_gaussians(load_bundle(sparse))
    write_ply(tmp_path / "sparse.ply", g.subset(np.arange(0, len(g), 10)))
    add_gaussians(sparse, tmp_path / "sparse.ply")
    out = tmp_path / "r.json"
    r = CliRunner().invoke(
        app,
        [
            "replay",
            str(sparse),
            str(tiny["scene"]),
            "--split",
            "test",
            "--refine",
            "--budget-ms",
            "2000",
            "--threads",
            "1",
            "--json",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    ref = json.loads(out.read_text())["refine"]
    assert ref["seeder"] == "onnx_initializer" and ref["calibration_ms"]["initializer_ms"] > 0
    # a generous budget: the initializer seeds every keyframe (measured 4 of 4, 2686 Gaussians added)
    assert ref["seeded_by"] == {"primary": ref["keyframes"], "scr": 0} and ref["gaussians_added"] > 1000
    assert ref["psnr_after"] > ref["psnr_before"] + 6.0  # measured 7.9 -> 18.1 dB
    assert ref["errors"] == []


def test_format_1_initializer_is_not_used_and_export_refuses_a_format_1_bundle(splat_bundle, tiny, tmp_path) -> None:
    """A format 1 bundle (SCR graph without features, initializer with its own encoder) still localizes; refinement
    says in one line that it seeds from SCR coordinates; export --splat onto it is a one-line error."""
    from acesplat.core.bundle import MANIFEST_NAME, load_bundle
    from acesplat.core.errors import InputError
    from edge.refine.bundle_models import splat_section
    from edge.refine.onnx_seeder import OnnxSeeder, onnx_seeder_for
    from export.splat_export import export_splat

    old = tmp_path / "old"
    shutil.copytree(splat_bundle, old)
    m = json.loads((old / MANIFEST_NAME).read_text())
    m["format_version"] = 1
    del m["scr"]["features"]
    (old / MANIFEST_NAME).write_text(json.dumps(m))
    b = load_bundle(old)
    said: list[str] = []
    assert onnx_seeder_for(b, warn=said.append) is None
    assert len(said) == 1 and "format 1" in said[0] and "SCR coordinates" in said[0]
    with pytest.raises(InputError, match="takes \\['gray'\\]") as e:  # an image-input graph is refused by name
        OnnxSeeder(b.scr_model("fp32"), splat_section(b))
    assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="format 1.*no features output.*re-export"):
        export_splat(old, splat_bundle.parent / "splat", tiny["map"])


def test_export_splat_refuses_a_splat_of_another_encoder(splat_bundle, tiny, tmp_path) -> None:
    from acesplat.core.bundle import MANIFEST_NAME
    from acesplat.core.errors import InputError
    from export.splat_export import export_splat

    other = tmp_path / "other"
    shutil.copytree(splat_bundle, other)
    m = json.loads((other / MANIFEST_NAME).read_text())
    m["scr"]["encoder"]["sha256"] = "0" * 64
    (other / MANIFEST_NAME).write_text(json.dumps(m))
    with pytest.raises(InputError, match="trained on features of encoder"):
        export_splat(other, splat_bundle.parent / "splat", tiny["map"])


def test_wait_parked_returns_only_after_the_running_piece_and_no_piece_starts_until_the_next_window() -> None:
    """What a paced session relies on: after preempt + wait_parked nothing of refinement runs until the next frame."""
    events: list[tuple[str, float]] = []

    class SlowSteps(_StepRefiner):
        def batch(self, kf, rep: BatchReport):
            self.started.set()
            step = CostEstimate(0.001, name="step")
            while (yield ("step", step, 0.0)):
                events.append(("start", time.perf_counter()))
                time.sleep(0.03)
                events.append(("end", time.perf_counter()))
            rep.outcome = "committed"

    ref = SlowSteps()
    w = RefineWorker(ref, KeyframeSelector(KeyframePolicy(min_inliers=0)), max_windows=4, step_windows=4)
    try:
        w.submit(_candidate("a", 30.0, 0.0))
        assert ref.started.wait(5.0)
        time.sleep(0.05)  # inside a step now or between two
        w.preempt()
        assert w.wait_parked(5.0)
        parked = time.perf_counter()
        time.sleep(0.1)  # a 'localization': the worker must stay parked
        quiet = [e for e in events if e[1] > parked]
        w.submit(_candidate("b", 30.0, 1.0))  # the next frame's window: steps resume
        time.sleep(0.05)
    finally:
        w.close()
    assert any(k == "end" for k, _ in events)
    assert quiet == []
    assert any(t > parked + 0.1 for _, t in events)


def blas_threads() -> dict[str, int]:
    """Threads of each loaded BLAS library, by file (a library can load mid-test)."""
    from threadpoolctl import threadpool_info

    return {p["filepath"]: p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}


def test_refinement_runs_blas_on_one_thread_and_restores_it(bundle_with_gaussians) -> None:
    """OpenBLAS workers busy-wait after a call: left multi-threaded, the worker's numpy work kept both cores
    spinning into the next localization. A session holds BLAS to one thread and gives the setting back."""
    from acesplat.apps.refine_cmd import refine_session
    from acesplat.core.bundle import load_bundle
    from edge.runtime import EdgeLocalizer

    before = blas_threads()
    b = load_bundle(bundle_with_gaussians)
    loc = EdgeLocalizer(b, "fp32", 1)
    session = refine_session(True, loc, b, 100.0, None, lambda msg: None)
    try:
        during = blas_threads()
        assert during and all(n == 1 for n in during.values())  # also a BLAS the kernels loaded after the start
    finally:
        session.close()
    after = blas_threads()
    assert {k: after[k] for k in before} == before


def test_a_session_that_fails_to_start_gives_the_thread_settings_back(bundle_with_gaussians) -> None:
    """The constructor limits BLAS and the rasterizer's threads first; if a later step raises, both come back."""
    from acesplat.core.bundle import load_bundle
    from acesplat.raster import get_num_threads
    from edge.refine.bundle_models import bundle_gaussians
    from edge.refine.session import RefineOptions, RefineSession
    from edge.runtime import EdgeLocalizer

    class BrokenSeeder:
        needs_features = False

        def __call__(self, *args, **kwargs):
            raise AssertionError("not reached")

        def time_once(self, fn) -> float:
            raise RuntimeError("initializer failed to load")

    before_blas, before_raster = blas_threads(), get_num_threads()
    b = load_bundle(bundle_with_gaussians)
    loc = EdgeLocalizer(b, "fp32", 1)
    opts = RefineOptions(budget_ms=100.0, raster_threads=1)
    with pytest.raises(RuntimeError, match="initializer failed"):
        RefineSession(loc.input_size, bundle_gaussians(b), opts, seeder=BrokenSeeder())
    after = blas_threads()
    assert {k: after[k] for k in before_blas} == before_blas and get_num_threads() == before_raster


def test_replay_whose_refinement_lowers_a_views_psnr_fails(tiny, bundle_with_gaussians, tmp_path, monkeypatch) -> None:
    """A refined map that renders worse than the loaded one (here its colours inverted at the end) fails the run:
    the JSON says so, a line says so, the exit code is 1, and the JSON is still written."""
    from edge.refine.refiner import Refiner

    real = Refiner.snapshot

    def spoiled(self):
        g = real(self)
        g.sh[:, 0] = -g.sh[:, 0]
        return g

    monkeypatch.setattr(Refiner, "snapshot", spoiled)
    out = tmp_path / "r.json"
    r = CliRunner().invoke(
        app,
        ["replay", str(bundle_with_gaussians), str(tiny["scene"]), "--refine", "--threads", "1", "--json", str(out)],
    )
    assert r.exit_code == 1, r.output
    ref = json.loads(out.read_text())["refine"]
    assert ref["failed"] and ref["views_harmed"] >= 1 and ref["psnr_worst_change_db"] < -ref["harm_tolerance_db"]
    assert ref["harmed"][0]["psnr_after"] < ref["harmed"][0]["psnr_before"]
    assert "refine FAILED: PSNR fell on" in r.output


def test_a_bundles_mapping_images_are_pinned_witnesses_and_no_view_ends_worse(tiny, tmp_path) -> None:
    """A bundle exported with --keyframes lends its mapping images (grey, surveyed poses) to the end-of-session check:
    pinned, spread over the viewpoints, and after the repair none is below the loaded map, nor any tracked frame."""
    from export.bundle_export import ExportOptions, export_bundle
    from export.splat_export import add_gaussians

    b = tmp_path / "kf"
    export_bundle(tiny["map"], b, ExportOptions(keyframes=True))
    frames = read_split(tiny["scene"], "train").frames
    g = concat_gaussians([depth_gaussians(f, 3, np.random.default_rng(0), 0.02, 0.15) for f in frames[:6:2]])
    write_ply(tmp_path / "start.ply", g)
    add_gaussians(b, tmp_path / "start.ply")

    from acesplat.core.bundle import load_bundle
    from edge.refine.session import RefineOptions, mapping_witnesses

    ws = mapping_witnesses(load_bundle(b), 5, 40)
    assert len(ws) == 5 and all(w.rgb.ndim == 2 and max(w.rgb.shape) == 40 for w in ws)
    assert mapping_witnesses(load_bundle(tiny["bundle"]), 5, 40) == []  # no keyframes, no pinned witnesses
    assert RefineOptions().pinned_witnesses > 0

    out = tmp_path / "r.json"
    r = CliRunner().invoke(
        app,
        ["replay", str(b), str(tiny["scene"]), "--split", "train", "--refine", "--budget-ms", "2000", "--threads", "1",
         "--json", str(out)],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    w = json.loads(out.read_text())["refine"]["witness"]
    assert w["pinned"] == 12 and w["witnesses"] == 12 + w["kept"] and w["kept"] == 12
    assert "witnesses checked" in r.output


def test_a_grey_witness_is_scored_on_the_renders_grey(tmp_path_factory) -> None:
    import cv2

    from edge.refine.guard import render_view
    from edge.refine.witness import Witness
    from tests.refine_scene import perturbed_map, rgb01, tiny_room

    fr = tiny_room(tmp_path_factory)[2]
    g = perturbed_map(tiny_room(tmp_path_factory)[:4])
    gray = cv2.cvtColor(fr.load_rgb(), cv2.COLOR_RGB2GRAY)
    w = Witness(fr.pose, fr.intrinsics, gray)
    r = render_view(g, fr.pose, fr.intrinsics, np.zeros(3))
    ref = cv2.cvtColor(np.ascontiguousarray(r.color, np.float32), cv2.COLOR_RGB2GRAY) - gray / 255.0
    assert w.mse(g, w.target(), np.zeros(3)) == pytest.approx(float(np.mean(ref**2)), rel=1e-4)
    assert rgb01(fr).shape[:2] == gray.shape
