"""`acesplat demo` end to end at a tiny size: every stage runs, the table and the JSON carry the numbers."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from acesplat.apps.cli import app


def test_tiny_demo_runs_every_stage_and_reports_refinement(tmp_path) -> None:
    out = tmp_path / "demo.json"
    r = CliRunner().invoke(
        app,
        [
            "demo",
            "--workdir",
            str(tmp_path / "w"),
            "--size",
            "64x80",
            "--frames",
            "12,4",
            "--map-steps",
            "60",
            "--splat-iterations",
            "3",
            "--refine-budget-ms",
            "500",
            "--json",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    s = json.loads(out.read_text())
    assert s["synth"]["train_frames"] == 12 and s["synth"]["size"] == [64, 80]
    assert (
        s["eval_align"]["frames"] == 4 and sum(s["eval_align"]["keyframe_alignment"].values()) == s["eval"]["localized"]
    )
    assert "eval (torch), aligned" in r.output
    # the corners start: corners of 12 views of 64x80 (80 cells each) triangulated between them; measured 35
    assert s["splat"]["iterations"] == 3 and s["splat"]["gaussians_final"] >= 30
    checks = s["export"]["checks"]
    assert {"fp32_vs_torch", "test_split", "splat_init_fp32_vs_torch", "splat_init_via_scr_int8_vs_torch"} <= set(
        checks
    )
    # The demo's head is untrained (zero residuals), so its graph's own parity is 0 / 0; a probe with a random output
    # layer checks the export path instead.
    assert (
        checks["splat_init_fp32_vs_torch"]["untrained_head"]
        and checks["splat_init_fp32_vs_torch"]["max_abs_output"] == 0
    )
    probe = checks["splat_init_probe_fp32_vs_torch"]
    assert probe["max_abs_output"] > 0.05 and probe["max_abs_diff"] < 1e-4 * max(1.0, probe["max_abs_output"])
    for k in ("replay_fp32", "replay_int8", "replay_refine"):
        assert s[k]["frames"] == 4
    ref = s["replay_refine"]["refine"]
    # the INT8 graph the device's check picks (the U8S8 twin where it is faster and as close to FP32)
    assert [c["precision"] for c in s["int8_check"]] == ["int8", "int8_vnni"]
    assert s["replay_refine"]["precision"] == s["replay_int8"]["precision"] in ("int8", "int8_vnni")
    assert ref["budget_ms"] == 500
    ref_precision = s["replay_refine"]["precision"]
    # a 60-step map localizes few test views, so refinement may add nothing; it must not make the map worse
    assert ref["psnr_views"] == 4 and 8.0 < ref["psnr_before"] < 30.0  # measured 13.6 dB
    assert ref["psnr_after"] >= ref["psnr_before"] - 0.5  # measured equal (no view localized)
    assert ref["seeder"] == "onnx_initializer" and ref["calibration_ms"]["initializer_ms"] > 0
    assert "+ refinement" in r.output and ref_precision in r.output and "PSNR" in r.output
    assert s["replay_paced"]["frames"] == 4 and "park" in ref["timing_ms"]
    renders = s["replay_refine"]["renders"]
    assert len(renders) == 3 and all(im["path"] in r.output for im in renders)
    for im in renders:
        png = (tmp_path / "w" / "refine_renders" / Path(im["path"]).name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and 5.0 < im["psnr_after"] < 40.0  # measured 7.0 to 16.4 dB
    stages = sum(v["seconds"] for v in s.values() if isinstance(v, dict) and "seconds" in v)
    assert s["seconds"] >= stages > 0 and (tmp_path / "w" / "bundle" / "splat_init.onnx").is_file()


def test_demo_bad_options_are_one_line_errors(tmp_path) -> None:
    for args, message in (
        (["--frames", "12"], "TRAIN,TEST"),
        (["--refine-budget-ms", "0"], "must be positive"),
        (["--size", "64by80"], "HxW"),
    ):
        r = CliRunner().invoke(app, ["demo", "--workdir", str(tmp_path / "w"), *args])
        assert r.exit_code == 2 and message in r.output and "Traceback" not in r.output, r.output
