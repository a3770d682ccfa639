"""The on-device INT8 check: check frames stored at export, the deviation figures, the bound, and the commands."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.core.camera import Intrinsics
from acesplat.core.check_frames import CheckFrames, deviation, load_check_frames, save_check_frames
from acesplat.core.errors import InputError
from edge.int8_check import Int8CheckConfig, bound_for, judge


def _frames(n: int = 2, h: int = 16, w: int = 24, stride: int = 8) -> CheckFrames:
    rng = np.random.default_rng(0)
    K = np.stack([Intrinsics.from_focal(20.0, w, h).K] * n)
    coords = rng.normal(size=(n, h // stride, w // stride, 3)).astype(np.float32)
    return CheckFrames(
        [f"f{i}" for i in range(n)], rng.integers(0, 256, (n, h, w), dtype=np.uint8), K, coords, coords + 0.01, stride
    )


def test_check_frames_round_trip(tmp_path: Path) -> None:
    f = _frames()
    save_check_frames(tmp_path / "c.npz", f)
    g = load_check_frames(tmp_path / "c.npz")
    assert g.names == f.names and g.stride == f.stride
    for k in ("gray", "K", "coords", "int8_coords"):
        np.testing.assert_array_equal(getattr(g, k), getattr(f, k))
    assert g.vnni_coords is None
    with pytest.raises(ValueError, match="no int8_vnni"):
        g.int8("int8_vnni")
    v = CheckFrames(f.names, f.gray, f.K, f.coords, f.int8_coords, f.stride, f.coords + 0.02)
    save_check_frames(tmp_path / "v.npz", v)
    np.testing.assert_array_equal(load_check_frames(tmp_path / "v.npz").int8("int8_vnni"), v.vnni_coords)


def test_check_frames_bad_file_names_it(tmp_path: Path) -> None:
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz"):
        load_check_frames(tmp_path / "junk.npz")
    f = _frames()
    np.savez(tmp_path / "short.npz", names=np.array(f.names), gray=f.gray, K=f.K, coords=f.coords[:, :1],
             int8_coords=f.int8_coords, stride=np.int64(8))  # fmt: skip
    with pytest.raises(InputError, match="short.npz: coords must be"):
        load_check_frames(tmp_path / "short.npz")
    np.savez(tmp_path / "twin.npz", names=np.array(f.names), gray=f.gray, K=f.K, coords=f.coords,
             int8_coords=f.int8_coords, vnni_coords=f.coords[:, :1], stride=np.int64(8))  # fmt: skip
    with pytest.raises(InputError, match="twin.npz: vnni_coords must be"):
        load_check_frames(tmp_path / "twin.npz")


def _grid_of_plane(intr: Intrinsics, T_c2w: np.ndarray, stride: int = 8) -> np.ndarray:
    """Scene coordinates (h, w, 3) of a fronto-parallel plane 3 m away, seen from ``T_c2w``, at the cell centres."""
    h, w = intr.height // stride, intr.width // stride
    u, v = np.meshgrid(np.arange(w) * stride + stride / 2, np.arange(h) * stride + stride / 2)
    depth = 3.0 + 0.5 * np.sin(u / 17.0) * np.cos(v / 13.0)
    cam = np.stack([(u - intr.cx) / intr.fx * depth, (v - intr.cy) / intr.fy * depth, depth], axis=-1)
    return (cam @ T_c2w[:3, :3].T + T_c2w[:3, 3]).astype(np.float32)


def test_deviation_of_a_shifted_grid_is_the_shift() -> None:
    """Every coordinate moved by the same vector c: coordinate deviation |c| everywhere, and the PnP pose moves by c
    (a rigid translation of the scene), rotation unchanged."""
    intr = Intrinsics.from_focal(200.0, 320, 240)
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    a = _grid_of_plane(intr, T)
    c = np.array([0.03, -0.04, 0.0], dtype=np.float32)  # |c| = 5 cm
    d = deviation([a, a], [a + c, a + c], [intr, intr], 8)
    assert d["coord_median"] == pytest.approx(0.05, abs=1e-6) and d["coord_p90"] == pytest.approx(0.05, abs=1e-6)
    assert d["pose_frames"] == 2
    assert d["pose_median_translation"] == pytest.approx(0.05, abs=2e-3)
    assert d["pose_median_rotation_deg"] < 0.05
    same = deviation([a], [a], [intr], 8)
    assert same["coord_median"] == 0.0 and same["pose_median_translation"] < 1e-6


def test_bound_is_tolerance_times_export_plus_slack() -> None:
    cfg = Int8CheckConfig(tolerance=1.5, slack=0.01, slack_deg=0.1)
    assert bound_for(0.04, 0.01, cfg) == pytest.approx(0.07)
    assert bound_for(None, 0.01, cfg) is None
    export = {"coord_median": 0.02, "coord_p90": 0.1, "pose_median_translation": 0.04,
              "pose_median_rotation_deg": 0.2, "pose_frames": 4, "frames": 4}  # fmt: skip
    ok = {**export, "coord_median": 0.039}  # bound 0.04
    bounds, failures = judge(ok, export, cfg)
    assert bounds["coord_median"] == pytest.approx(0.04) and bounds["pose_median_rotation_deg"] == pytest.approx(0.4)
    assert failures == []
    _, failures = judge({**export, "coord_median": 0.041}, export, cfg)
    assert len(failures) == 1 and failures[0].startswith("coordinate median 4.10 cm > 4.00 cm")
    _, failures = judge({**export, "pose_frames": 3}, export, cfg)
    assert failures and "3 of 4 frames" in failures[0]


# ----------------------------------------------------------------------------------- on the tiny bundle
def test_export_stores_check_frames_and_figures(tiny) -> None:
    from acesplat.core.bundle import ROLE_INT8_CHECK, load_bundle
    from acesplat.core.check_frames import bundle_check_frames

    b = load_bundle(tiny["bundle"])
    frames = bundle_check_frames(b)
    assert len(frames) == 4 and frames.gray.shape[1:] == b.input_size and b.has(ROLE_INT8_CHECK)
    dev = tiny["manifest"]["checks"]["int8_vs_fp32"]
    assert dev["frames"] == 4 and dev["coord_median"] > 0 and dev["cpu_isa"] is not None
    # the manifest's figures are the stored coordinates' deviation
    intr = [frames.intrinsics(i) for i in range(4)]
    again = deviation(list(frames.coords), list(frames.int8_coords), intr, b.output_stride)
    assert again["coord_median"] == pytest.approx(dev["coord_median"], rel=1e-6)


def test_check_passes_on_the_export_machine(tiny) -> None:
    from acesplat.core.bundle import load_bundle
    from edge.int8_check import check_int8

    (rep,) = check_int8(load_bundle(tiny["bundle"]), Int8CheckConfig(frames=2), threads=1)
    assert rep.passed, rep.failures
    assert rep.fp32_vs_export["coord_max"] < 1e-3  # the same FP32 graph on the same CPU
    assert len(rep.frames) == 2 and rep.runtime["onnxruntime"]
    assert "INT8 check passed on 2 frames (ISA" in rep.line()


def _perturbed_bundle(tiny, dst: Path, precisions: tuple[str, ...] = ("int8", "int8_vnni")) -> Path:
    """A copy of the tiny bundle whose INT8 graphs of ``precisions`` have their weights scrambled and whose manifest
    lists the new hashes: an intact bundle with bad INT8 models."""
    import onnx
    from onnx import numpy_helper

    from acesplat.core.bundle import PRECISION_ROLES, describe_file, load_bundle, write_manifest

    shutil.copytree(tiny["bundle"], dst)
    b = load_bundle(dst, verify=False)
    roles = {PRECISION_ROLES[p] for p in precisions}
    rng = np.random.default_rng(1)
    for role in roles:
        path = dst / b.files[role].path
        model = onnx.load(str(path))
        for init in model.graph.initializer:
            w = numpy_helper.to_array(init)
            if w.dtype in (np.int8, np.uint8) and w.size > 64:
                init.CopyFrom(numpy_helper.from_array(rng.permutation(w.ravel()).reshape(w.shape), init.name))
        onnx.save(model, str(path))
    files = [describe_file(dst, f.path, f.role) if f.role in roles else f for f in b.files.values()]
    write_manifest(dst, b.manifest, files, version=b.format_version)
    return dst


def test_a_perturbed_int8_model_fails_the_check_and_is_refused(tiny, tmp_path: Path) -> None:
    from acesplat.apps.edge_cli import app

    bad = _perturbed_bundle(tiny, tmp_path / "bad")
    r = CliRunner().invoke(app, ["check", str(bad), "--json", str(tmp_path / "c.json"), "--threads", "1"])
    assert r.exit_code == 1, r.output
    rep = json.loads((tmp_path / "c.json").read_text())
    assert rep["passed"] is False and rep["chosen"] is None and rep["failures"]
    assert [r["precision"] for r in rep["reports"]] == ["int8", "int8_vnni"]
    r = CliRunner().invoke(app, ["replay", str(bad), str(tiny["scene"]), "--int8", "--threads", "1",
                                 "--json", str(tmp_path / "r.json")])  # fmt: skip
    assert r.exit_code == 2
    lines = [x for x in r.output.splitlines() if x.startswith("error:")]
    assert len(lines) == 1 and "scr.int8.onnx: INT8 deviates from FP32 on this CPU" in lines[0]
    assert "--skip-int8-check" in lines[0]
    assert not (tmp_path / "r.json").exists()  # nothing written
    r = CliRunner().invoke(app, ["localize", str(bad), "--source", f"replay:{tiny['scene']}/test", "--int8",
                                 "--frames", "1", "--threads", "1", "--quiet"])  # fmt: skip
    assert r.exit_code == 2 and "INT8 deviates from FP32" in r.output
    r = CliRunner().invoke(app, ["replay", str(bad), str(tiny["scene"]), "--int8", "--threads", "1",
                                 "--skip-int8-check"])  # fmt: skip
    assert r.exit_code == 0, r.output


def test_export_writes_the_u8s8_twin_with_its_figures(tiny, tmp_path: Path) -> None:
    from acesplat.apps.cli import app
    from acesplat.core.bundle import ROLE_SCR_INT8_VNNI, load_bundle
    from acesplat.core.check_frames import bundle_check_frames

    b = load_bundle(tiny["bundle"])
    assert b.has(ROLE_SCR_INT8_VNNI) and b.scr["precisions"] == ["fp32", "int8", "int8_vnni"]
    assert "U8S8" in b.scr["int8_vnni_scheme"] and "U8U8" in b.scr["int8_scheme"]
    frames = bundle_check_frames(b)
    dev = tiny["manifest"]["checks"]["int8_vnni_vs_fp32"]
    intr = [frames.intrinsics(i) for i in range(len(frames))]
    again = deviation(list(frames.coords), list(frames.int8("int8_vnni")), intr, b.output_stride)
    assert again["coord_median"] == pytest.approx(dev["coord_median"], rel=1e-6)
    assert not np.array_equal(frames.vnni_coords, frames.int8_coords)  # two graphs, two sets of coordinates
    assert tiny["manifest"]["checks"]["test_split"]["int8_vnni"]["frames"] > 0
    r = CliRunner().invoke(app, ["export", str(tiny["map"]), "-o", str(tmp_path / "b"), "--int8", "--no-int8-vnni",
                                 "--check-frames", "1"])  # fmt: skip
    assert r.exit_code == 0, r.output
    b = load_bundle(tmp_path / "b")
    assert not b.has(ROLE_SCR_INT8_VNNI) and bundle_check_frames(b).vnni_coords is None
    assert "int8_vnni_vs_fp32" not in b.manifest["checks"]


def test_a_bad_u8s8_twin_is_refused_and_the_default_runs(tiny, tmp_path: Path, monkeypatch) -> None:
    from acesplat.apps.edge_cli import app
    from acesplat.core.bundle import load_bundle
    from edge import int8_check
    from edge.int8_check import choose_int8

    monkeypatch.setattr(int8_check, "u8s8_probe_error", lambda provider="cpu": 0.0)  # as on a VNNI CPU
    bad = _perturbed_bundle(tiny, tmp_path / "bad", ("int8_vnni",))
    chosen, reports = choose_int8(load_bundle(bad), Int8CheckConfig(frames=2), threads=1)
    assert chosen == "int8" and reports[0].passed and not reports[1].passed
    assert any("x the default graph's" in f for f in reports[1].failures)
    assert reports[1].u8s8_probe_error == 0.0 and reports[0].u8s8_probe_error is None  # the default is U8U8
    r = CliRunner().invoke(app, ["replay", str(bad), str(tiny["scene"]), "--int8", "--threads", "1", "--no-tracking",
                                 "--json", str(tmp_path / "r.json")])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "r.json").read_text())["precision"] == "int8"
    # the default broken, the twin verified: --int8 runs the twin
    bad2 = _perturbed_bundle(tiny, tmp_path / "bad2", ("int8",))
    chosen, reports = choose_int8(load_bundle(bad2), Int8CheckConfig(frames=2), threads=1)
    assert chosen == "int8_vnni" and not reports[0].passed and reports[1].passed
    # profile measures the graph --int8 runs, not the default one
    r = CliRunner().invoke(app, ["profile", str(bad2), "--int8", "--frames", "2", "--warmup", "0", "--threads", "1",
                                 "--json", str(tmp_path / "p.json")])  # fmt: skip
    assert r.exit_code == 0, r.output
    p = json.loads((tmp_path / "p.json").read_text())
    assert p["precision"] == "int8_vnni" and len(p["header"]["model_sha256"]["int8_vnni"]) == 64
    r = CliRunner().invoke(app, ["profile", str(bad2), "--compare", "--frames", "2", "--warmup", "0", "--threads",
                                 "1", "--json", str(tmp_path / "c.json")])  # fmt: skip
    assert r.exit_code == 0, r.output
    c = json.loads((tmp_path / "c.json").read_text())
    assert c["precision"] == ["fp32", "int8_vnni"] and c["int8_inference_speedup_p50"] > 0


def test_the_fastest_passing_graph_runs(monkeypatch) -> None:
    from edge import int8_check

    def rep(p: str, ok: bool, ms: float):
        return int8_check.Int8CheckReport(ok, [] if ok else ["x"], {}, {}, {}, {}, {"int8": ms}, {}, precision=p)

    cases = [
        ([rep("int8", True, 60.0), rep("int8_vnni", True, 30.0)], "int8_vnni"),
        ([rep("int8", True, 60.0), rep("int8_vnni", True, 57.0)], "int8"),  # within INT8_MIN_GAIN: the default
        ([rep("int8", True, 60.0), rep("int8_vnni", False, 30.0)], "int8"),
        ([rep("int8", False, 60.0), rep("int8_vnni", False, 30.0)], None),
    ]
    monkeypatch.setattr(int8_check, "int8_precisions", lambda b: ["int8", "int8_vnni"])
    for reports, want in cases:
        monkeypatch.setattr(int8_check, "check_int8", lambda *a, _r=reports, **k: _r)
        assert int8_check.choose_int8(None)[0] == want


def test_check_command_passes_and_replay_int8_runs_the_check(tiny, tmp_path: Path) -> None:
    from acesplat.apps.edge_cli import app

    r = CliRunner().invoke(app, ["check", str(tiny["bundle"]), "--frames", "2", "--threads", "1"])
    assert r.exit_code == 0, r.output
    assert "INT8 check passed on 2 frames" in r.output and "onnxruntime" in r.output
    r = CliRunner().invoke(app, ["check", str(tiny["bundle"]), "--frames", "0"])
    assert r.exit_code == 2 and "--frames must be positive" in r.output


def test_a_bundle_without_check_frames_is_refused_for_int8(tiny, tmp_path: Path) -> None:
    from acesplat.apps.edge_cli import app
    from acesplat.core.bundle import ROLE_INT8_CHECK, load_bundle, write_manifest

    old = tmp_path / "old"
    shutil.copytree(tiny["bundle"], old)
    b = load_bundle(old, verify=False)
    (old / b.files[ROLE_INT8_CHECK].path).unlink()
    write_manifest(old, b.manifest, [f for f in b.files.values() if f.role != ROLE_INT8_CHECK])
    r = CliRunner().invoke(app, ["replay", str(old), str(tiny["scene"]), "--int8", "--threads", "1"])
    assert r.exit_code == 2 and "no INT8 check frames" in r.output and "re-export" in r.output
    r = CliRunner().invoke(app, ["check", str(old)])
    assert r.exit_code == 2


def test_unknown_int8_types_are_refused_in_one_line(tiny, tmp_path: Path) -> None:
    from acesplat.apps.cli import app

    r = CliRunner().invoke(app, ["export", str(tiny["map"]), "-o", str(tmp_path / "b"), "--int8", "--int8-types",
                                 "s8u8"])  # fmt: skip
    assert r.exit_code == 2 and "--int8-types must be one of u8s8, s8s8, u8u8" in r.output
    assert not (tmp_path / "b").exists()


def test_the_shipped_u8s8_probe_is_the_generators_and_its_exact_output_is_analytic() -> None:
    """edge/u8s8_probe.onnx holds export.u8s8_probe's graph; its U8U8 output is 255 x the column sums of the weights
    on every CPU; the U8S8 output is exact or off by a large fraction (saturated), never slightly."""
    import onnx
    import onnxruntime as ort

    from edge import int8_check
    from export.u8s8_probe import PROBE_INPUT, probe_model, probe_weights

    shipped, made = onnx.load(str(int8_check.U8S8_PROBE)), probe_model()
    assert [n.op_type for n in shipped.graph.node] == [n.op_type for n in made.graph.node] == ["MatMulInteger"] * 2
    for a, b in zip(shipped.graph.initializer, made.graph.initializer, strict=True):
        np.testing.assert_array_equal(onnx.numpy_helper.to_array(a), onnx.numpy_helper.to_array(b))
    assert PROBE_INPUT == int8_check.U8S8_PROBE_INPUT
    sess = ort.InferenceSession(str(int8_check.U8S8_PROBE), providers=["CPUExecutionProvider"])
    a = np.full(sess.get_inputs()[0].shape, PROBE_INPUT, dtype=np.uint8)
    (exact,) = sess.run(["Y_exact"], {"A": a})
    b = probe_weights().astype(np.int64)
    np.testing.assert_array_equal(exact, np.broadcast_to(PROBE_INPUT * b.sum(0), exact.shape))
    assert (PROBE_INPUT * (b[0::2] + b[1::2]) > 32767).all()  # every pair sum overflows int16
    err = int8_check.u8s8_probe_error("cpu")
    assert err == 0.0 or err > 0.1, err
    assert int8_check.u8s8_probe_error("cuda") is None  # the probe reaches the CPU's kernels only


def test_a_saturating_cpu_refuses_the_u8s8_twin_by_name(tiny, tmp_path: Path, monkeypatch) -> None:
    """On a CPU whose U8S8 products saturate (x86 without VNNI), the twin is refused before its figures are weighed,
    the U8U8 default runs, and the report and the check's JSON carry the probe."""
    from acesplat.apps.edge_cli import app
    from acesplat.core.bundle import load_bundle
    from edge import int8_check

    monkeypatch.setattr(int8_check, "u8s8_probe_error", lambda provider="cpu": 0.38)
    chosen, reports = int8_check.choose_int8(load_bundle(tiny["bundle"]), Int8CheckConfig(frames=2), threads=1)
    assert chosen == "int8" and reports[0].passed and not reports[1].passed
    assert "U8S8 products saturate" in reports[1].failures[0] and "38%" in reports[1].failures[0]
    r = CliRunner().invoke(app, ["check", str(tiny["bundle"]), "--json", str(tmp_path / "c.json"), "--threads", "1",
                                 "--frames", "2"])  # fmt: skip
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "c.json").read_text())
    assert rep["chosen"] == "int8" and rep["reports"][1]["u8s8_probe_error"] == 0.38
    assert "--int8 runs int8 on this CPU" in r.output and "saturates (38% off)" in r.output


def test_a_graph_other_than_the_default_must_be_as_close_as_the_default_on_this_cpu(tiny) -> None:
    """judge_graphs against synthetic grids: a twin 10% further from FP32 than the default passes, 60% fails on its
    p90, even where both stay inside the export's own (loose) figures; a twin alone is a caller's error."""
    from acesplat.core.bundle import load_bundle
    from acesplat.core.check_frames import bundle_check_frames
    from edge.int8_check import judge_graphs

    b = load_bundle(tiny["bundle"])
    frames = bundle_check_frames(b)
    ref = [frames.coords[i] for i in range(2)]
    rng = np.random.default_rng(1)
    noise = [rng.normal(scale=0.02, size=r.shape).astype(np.float32) for r in ref]
    loose = Int8CheckConfig(tolerance=1000.0, slack=1.0, slack_deg=90.0)
    out = judge_graphs(b, frames, ref, {"int8": [r + e for r, e in zip(ref, noise, strict=True)],
                                        "int8_vnni": [r + 1.1 * e for r, e in zip(ref, noise, strict=True)]},
                       Int8CheckConfig(tolerance=1000.0, slack=0.0, slack_deg=90.0))  # fmt: skip
    assert out["int8"][3] == [] and out["int8_vnni"][3] == []
    out = judge_graphs(b, frames, ref, {"int8": [r + e for r, e in zip(ref, noise, strict=True)],
                                        "int8_vnni": [r + 1.6 * e for r, e in zip(ref, noise, strict=True)]},
                       Int8CheckConfig(tolerance=1000.0, slack=0.0, slack_deg=90.0))  # fmt: skip
    assert out["int8"][3] == [] and any("p90" in f and "1.2 x the default graph's" in f for f in out["int8_vnni"][3])
    with pytest.raises(ValueError, match="beside the default"):
        judge_graphs(b, frames, ref, {"int8_vnni": ref}, loose)
