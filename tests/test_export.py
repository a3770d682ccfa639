"""`acesplat export`: the bundle it writes, the checks it runs, and its refusals."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.core.bundle import load_bundle
from acesplat.core.errors import InputError
from acesplat.scr.encoders import file_sha256


def test_manifest_describes_the_bundle(tiny) -> None:
    b = load_bundle(tiny["bundle"])
    m = b.manifest
    assert b.input_size == (64, 80)  # the map's short side (64) with the training images' 4:5 aspect
    assert m["scr"]["output_stride"] == 8 and m["scr"]["output_size"] == [8, 10]
    assert m["scr"]["normalization"]["mean"] == 0.4 and m["scr"]["normalization"]["std"] == 0.25
    assert len(m["scr"]["mean_offset"]) == 3
    assert m["scr"]["encoder"]["sha256"] == file_sha256(tiny["encoder"])  # the encoder the map was trained with
    assert {f.role for f in b.files.values()} == {"scr_fp32", "scr_int8", "scr_int8_vnni", "int8_check"}
    assert m["format_version"] == 2
    assert m["scr"]["features"]["name"] == "features" and m["scr"]["features"]["shape"] == [1, 32, 8, 10]
    assert m["created_by"].startswith("acesplat-edge") and m["scene"]["name"] == "room"


def test_fp32_graph_matches_torch(tiny) -> None:
    """Recorded self-check, and an independent run of the bundle against the map in torch."""
    import torch

    from acesplat.core.preprocess import to_gray_input
    from acesplat.core.scene import read_split
    from acesplat.scr.mapfile import encoder_for_map, load_map
    from edge.inference import ScrSession

    par = tiny["manifest"]["checks"]["fp32_vs_torch"]
    assert par["max_abs_diff_fraction"] < 1e-5
    assert par["pose_max_translation_diff_m"] < 1e-3 and par["pose_max_rotation_diff_deg"] < 1e-2
    m = load_map(tiny["map"])
    net = m.network(encoder_for_map(m, tiny["map"]))
    sess = ScrSession(Path(tiny["bundle"]) / "scr.onnx", (64, 80), threads=1)
    f = read_split(tiny["scene"], "test").frames[1]
    gray, _ = to_gray_input(f.load_rgb(), f.intrinsics, (64, 80))
    with torch.no_grad():
        ref = net(torch.from_numpy(gray).float()[None, None])[0].permute(1, 2, 0).numpy()
    assert np.abs(sess.run(gray) - ref).max() < 1e-4
    # The encoder features output (what the splat initializer takes), from the same run as the coordinates.
    assert par["features_max_abs_diff"] < 1e-5 * max(1.0, par["features_max_abs"])
    coords, feats = sess.run_with_features(gray)
    with torch.no_grad():
        from acesplat.scr.network import normalize_gray

        ref_feats = net.encoder(normalize_gray(torch.from_numpy(gray).float()[None, None]))[0].numpy()
    assert sess.has_features and np.array_equal(coords, sess.run(gray))
    assert feats.shape == (32, 8, 10) and np.abs(feats - ref_feats).max() < 1e-4 * max(1.0, np.abs(ref_feats).max())


def test_graph_takes_other_multiples_of_8_and_a_static_one_only_its_size(tiny, tmp_path: Path) -> None:
    """The bundle's graph is dynamic in H and W (the edge runs it smaller under --align): at 48x56 it equals the
    map in torch at 48x56; a graph exported static takes its own size only, and both refuse a size off the grid."""
    import torch

    from acesplat.scr.mapfile import encoder_for_map, load_map
    from edge.inference import ScrSession
    from export.onnx_graph import export_scr_onnx

    assert load_bundle(tiny["bundle"]).dynamic_size and tiny["manifest"]["scr"]["dynamic_size"] is True
    m = load_map(tiny["map"])
    net = m.network(encoder_for_map(m, tiny["map"]))
    sess = ScrSession(Path(tiny["bundle"]) / "scr.onnx", (64, 80), threads=1)
    gray = np.random.default_rng(5).integers(0, 256, (48, 56), dtype=np.uint8)
    with torch.no_grad():
        ref = net(torch.from_numpy(gray).float()[None, None])[0].permute(1, 2, 0).numpy()
    assert sess.dynamic and sess.accepts((48, 56)) and not sess.accepts((48, 60))
    out = sess.run(gray)
    assert out.shape == (6, 7, 3) and np.abs(out - ref).max() < 1e-4
    with pytest.raises(ValueError, match="multiples of 8"):
        sess.run(np.zeros((48, 60), np.uint8))
    static = ScrSession(export_scr_onnx(net, (64, 80), tmp_path / "static.onnx", dynamic=False), (64, 80), threads=1)
    assert not static.dynamic and static.accepts((64, 80)) and not static.accepts((48, 56))
    with pytest.raises(ValueError, match=r"\(64, 80\)"):
        static.run(gray)
    with pytest.raises(InputError, match="does not match the bundle input size"):
        ScrSession(tmp_path / "static.onnx", (48, 56), threads=1)


def test_int8_self_check_keeps_most_frames_localized(tiny) -> None:
    acc = tiny["manifest"]["checks"]["test_split"]
    fp32, int8 = acc["fp32"], acc["int8"]
    assert fp32["localized"] == fp32["frames"] == 4
    assert fp32["median_translation_m"] < 0.25 and fp32["median_rotation_deg"] < 6.0  # measured 18.6 cm, 4.4 deg
    assert int8["localized"] >= 3  # measured 4
    assert int8["median_translation_m"] < 0.3 and int8["median_rotation_deg"] < 7.0  # measured 21.7 cm, 4.7 deg
    assert tiny["manifest"]["checks"]["int8_calibration_frames"] == 12


def test_int8_graph_is_quantized(tiny) -> None:
    import onnx

    g = onnx.load(str(Path(tiny["bundle"]) / "scr.int8.onnx")).graph
    ops = [n.op_type for n in g.node]
    assert ops.count("QuantizeLinear") > 5 and "DequantizeLinear" in ops
    assert [o.name for o in g.output] == ["coords", "features"]  # the quantizer keeps both outputs
    # activations uint8 (U8U8 by default: ExportOptions.int8_types)
    inits = {i.name: i for i in g.initializer}
    q_types = {
        inits[n.input[2]].data_type
        for n in g.node
        if n.op_type == "QuantizeLinear" and len(n.input) > 2 and n.input[2] in inits
    }
    assert onnx.TensorProto.UINT8 in q_types


def test_bad_size_and_missing_map_are_one_line_errors(tiny, tmp_path: Path) -> None:
    from acesplat.apps.cli import app
    from export.bundle_export import ExportOptions, export_bundle

    with pytest.raises(InputError, match="multiple of 8"):
        export_bundle(tiny["map"], tmp_path / "b", ExportOptions(size_hw=(60, 80)))
    r = CliRunner().invoke(app, ["export", str(tmp_path / "missing.map"), "-o", str(tmp_path / "b")])
    assert r.exit_code == 2
    assert "map file not found" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(app, ["export", str(tiny["map"]), "-o", str(tmp_path / "b"), "--size", "64by80"])
    assert r.exit_code == 2 and "HxW" in r.output


def test_refuses_to_replace_a_folder_that_is_not_a_bundle(tiny, tmp_path: Path) -> None:
    from export.bundle_export import ExportOptions, export_bundle

    keep = tmp_path / "precious"
    keep.mkdir()
    (keep / "notes.txt").write_text("do not delete")
    with pytest.raises(InputError, match="not a bundle"):
        export_bundle(tiny["map"], keep, ExportOptions())
    assert (keep / "notes.txt").read_text() == "do not delete"
    assert not list(tmp_path.glob(".precious.tmp-*"))


def test_int8_needs_the_training_images(tiny, tmp_path: Path) -> None:
    from export.bundle_export import ExportOptions, export_bundle

    with pytest.raises(InputError, match="calibrates on the map's training images"):
        export_bundle(
            tiny["map"], tmp_path / "b", ExportOptions(int8=True, scene_path=tmp_path / "gone", size_hw=(64, 80))
        )


def test_int8_keeps_the_encoders_first_and_the_heads_last_layers_float(tiny) -> None:
    import onnx

    from export.quantize import FLOAT_HEAD_CONVS, FLOAT_LEAD_CONVS

    for name in ("scr.int8.onnx", "scr.int8.u8s8.onnx"):
        g = onnx.load(str(Path(tiny["bundle"]) / name)).graph
        produced_by = {o: n.op_type for n in g.node for o in n.output}
        convs = [n for n in g.node if n.op_type == "Conv"]
        dequantized = [produced_by.get(c.input[1]) == "DequantizeLinear" for c in convs]
        middle = len(convs) - FLOAT_LEAD_CONVS - FLOAT_HEAD_CONVS
        assert dequantized == [False] * FLOAT_LEAD_CONVS + [True] * middle + [False] * FLOAT_HEAD_CONVS, name
        # the float layers' activations are float too: the first quantized layer's input is quantized once, after
        # the last float ReLU, and nothing before it is
        first_q = convs[FLOAT_LEAD_CONVS]
        assert produced_by[first_q.input[0]] == "DequantizeLinear", name
        lead_outputs = {o for c in convs[:FLOAT_LEAD_CONVS] for o in c.output}
        assert not any(n.op_type == "QuantizeLinear" and n.input[0] in lead_outputs for n in g.node), name


def test_onnxruntime_runs_the_float_layers_in_float(tiny, tmp_path: Path) -> None:
    """onnxruntime quantizes a float convolution's weights itself when its input comes out of a DequantizeLinear
    (to int8: the U8S8 kernels that can saturate without VNNI). The float layers the export keeps sit at the graph's
    ends, where that does not happen: the optimized graph runs them as float Conv and only the middle as QLinearConv."""
    import onnx
    import onnxruntime as ort

    from edge.inference import session_options
    from export.quantize import FLOAT_HEAD_CONVS, FLOAT_LEAD_CONVS

    so = session_options(1)
    so.optimized_model_filepath = str(tmp_path / "optimized.onnx")
    ort.InferenceSession(str(Path(tiny["bundle"]) / "scr.int8.onnx"), so, providers=["CPUExecutionProvider"])
    ops = [n.op_type for n in onnx.load(so.optimized_model_filepath).graph.node if "Conv" in n.op_type]
    middle = len(ops) - FLOAT_LEAD_CONVS - FLOAT_HEAD_CONVS
    assert ops == ["Conv"] * FLOAT_LEAD_CONVS + ["QLinearConv"] * middle + ["Conv"] * FLOAT_HEAD_CONVS


def test_dense_bundle_predicts_every_4th_pixel_and_the_edge_localizes_with_it(tiny, tmp_path: Path) -> None:
    from edge.replay import replay_split
    from edge.runtime import EdgeLocalizer
    from export.bundle_export import ExportOptions, export_bundle

    rep = export_bundle(tiny["map"], tmp_path / "dense", ExportOptions(dense=True))
    scr = rep.manifest["scr"]
    assert scr["output_stride"] == 4 and scr["output_size"] == [16, 20] and scr["output"]["shape"] == [1, 3, 16, 20]
    assert scr["features"]["shape"] == [1, 32, 16, 20] and "(4j+4, 4i+4)" in scr["output"]["content"]
    assert rep.manifest["checks"]["fp32_vs_torch"]["max_abs_diff_fraction"] < 1e-5  # measured 1.1e-6
    b = load_bundle(tmp_path / "dense")
    s = replay_split(EdgeLocalizer(b, "fp32", 1), tiny["scene"], "test")
    assert s["frames"] == 4 and s["localized"] == 4
    # measured 24.9 cm / 6.0 deg (AMD EPYC, AVX2), 30.5 cm / 9.0 deg (Xeon with AMX): 4 frames of a tiny map
    assert s["median_translation_m"] < 0.35 and s["median_rotation_deg"] < 10.0


def test_dense_bundles_carry_no_gaussians_and_other_strides_are_refused(tiny, tmp_path: Path) -> None:
    from acesplat.apps.cli import app

    r = CliRunner().invoke(
        app, ["export", str(tiny["map"]), "-o", str(tmp_path / "b"), "--dense", "--splat", str(tmp_path / "splat")]
    )
    assert r.exit_code == 2 and "drop --dense" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "b").exists()
    bad = tmp_path / "bad"
    shutil.copytree(tiny["bundle"], bad)
    m = json.loads((bad / "manifest.json").read_text())
    m["scr"]["output_stride"] = 2
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(InputError, match="output_stride must be 8 or 4"):
        load_bundle(bad, verify=False)


def kf_scene_args(tmp_path: Path, tiny) -> list[str]:
    return [str(tmp_path / "kf"), str(tiny["scene"])]


def test_keyframes_ride_in_the_bundle_and_the_edge_aligns_to_them(tiny, tmp_path: Path) -> None:
    from acesplat.align.keyframe_align import size_for_scr
    from acesplat.apps.edge_cli import app as edge_app
    from export.bundle_export import ExportOptions, export_bundle

    rep = export_bundle(tiny["map"], tmp_path / "kf", ExportOptions(keyframes=True))
    assert rep.manifest["keyframes"]["count"] == 12 and rep.manifest["keyframes"]["image_size"] == [64, 80]
    b = load_bundle(tmp_path / "kf")
    from acesplat.align.keyframe_set import bundle_keyframes

    ks = bundle_keyframes(b)
    assert len(ks) == 12 and ks.gray.shape == (12, 64, 80) and ks.stride == 4 and np.mean(ks.depth > 0) > 0.5
    out = tmp_path / "replay.json"
    r = CliRunner().invoke(
        edge_app, ["replay", str(tmp_path / "kf"), str(tiny["scene"]), "--align", "--json", str(out)]
    )
    assert r.exit_code == 0, r.output
    s = json.loads(out.read_text())
    assert sum(s["keyframe_alignment"].values()) == s["localized"] == 4
    assert "align" in s["timing_ms"] and s["median_translation_m"] < 0.25  # measured 18.6 cm
    # the views near enough to a keyframe to be aligned land within a few millimetres (measured 1 of 4, 0.8 cm)
    aligned = sorted(f["translation_m"] for f in s["per_frame"])[: s["keyframe_alignment"].get("aligned", 0)]
    assert len(aligned) >= 1 and max(aligned) < 0.02, s["per_frame"]
    assert s["align_warp"] == "keyframe" and s["align_matcher"] == "sparse"
    assert s["scr_size"] == s["input_size"] == [64, 80]  # at most PreciseSettings.scr_short_side: not made smaller
    # tracking (no --align): the SCR frames of a keyframe bundle get the same precise keyframe alignment
    r = CliRunner().invoke(edge_app, ["replay", str(tmp_path / "kf"), str(tiny["scene"]), "--json", str(out)])
    assert r.exit_code == 0, r.output
    t = json.loads(out.read_text())
    assert t["tracking_enabled"] and t["align_matcher"] == "sparse" and t["scr"] + t["reanchors"] >= 1
    assert sum(t["keyframe_alignment"].values()) >= t["scr"] + t["reanchors"]
    # SCR on a smaller copy (48x64), the alignment on the full image
    r = CliRunner().invoke(
        edge_app,
        ["replay", str(tmp_path / "kf"), str(tiny["scene"]), "--align", "--align-scr-side", "56", "--json", str(out)],
    )
    assert r.exit_code == 0 and "SCR at 56x72" in r.output, r.output
    small = json.loads(out.read_text())
    assert small["scr_size"] == [56, 72] and small["input_size"] == [64, 80]
    # the tiny map at 56x72 starts 65 cm off, beyond the alignment: each frame is solved again at the bundle's size,
    # so the run ends where the full-size one did
    assert small["keyframe_alignment"] == s["keyframe_alignment"]
    assert small["full_size_retries"] == small["localized"] == 4 and s["full_size_retries"] == 0
    assert small["median_translation_m"] == pytest.approx(s["median_translation_m"], abs=1e-9)
    with pytest.raises(ValueError, match="at least 8"):
        size_for_scr((64, 80), 4)
    r = CliRunner().invoke(edge_app, ["replay", *kf_scene_args(tmp_path, tiny), "--align", "--align-scr-side", "4"])
    assert r.exit_code == 2 and "--align-scr-side must be at least 8 pixels" in r.output, r.output
    assert size_for_scr((360, 544), 240) == (240, 360) and size_for_scr((240, 320), 240) == (240, 320)
    assert size_for_scr((240, 320), 480) == (240, 320)  # never up
    # the query's own SCR depth warping the keyframes: recorded, and a warp that does not exist is refused
    kf_scene = [str(tmp_path / "kf"), str(tiny["scene"])]
    dense_query = ["--align", "--align-matcher", "dense", "--align-warp", "query"]
    r = CliRunner().invoke(edge_app, ["replay", *kf_scene, *dense_query, "--json", str(out)])
    assert r.exit_code == 0, r.output
    q = json.loads(out.read_text())
    assert q["align_warp"] == "query" and sum(q["keyframe_alignment"].values()) == q["localized"] == 4
    r = CliRunner().invoke(edge_app, ["replay", str(tmp_path / "kf"), str(tiny["scene"]), "--align-warp", "splat"])
    assert r.exit_code == 2 and "Traceback" not in r.output
    assert "--align-warp must be one of keyframe, query" in r.output
    r = CliRunner().invoke(edge_app, ["replay", str(tmp_path / "kf"), str(tiny["scene"]), "--align-warp", "query"])
    assert r.exit_code == 2 and "add --align-matcher dense" in r.output
    # the sparse matcher (keyframe corners tracked by Lucas-Kanade): recorded, and an unknown one refused
    r = CliRunner().invoke(edge_app, ["replay", *kf_scene, "--align", "--align-matcher", "sparse", "--json", str(out)])
    assert r.exit_code == 0, r.output
    q = json.loads(out.read_text())
    assert q["align_matcher"] == "sparse" and sum(q["keyframe_alignment"].values()) == q["localized"] == 4
    r = CliRunner().invoke(edge_app, ["replay", str(tmp_path / "kf"), str(tiny["scene"]), "--align-matcher", "sift"])
    assert r.exit_code == 2 and "--align-matcher must be one of dense, sparse" in r.output
    # a bundle without keyframes, and one whose keyframes were altered, are refused in one line
    r = CliRunner().invoke(edge_app, ["replay", str(tiny["bundle"]), str(tiny["scene"]), "--align"])
    assert r.exit_code == 2 and "re-export with --keyframes" in r.output and "Traceback" not in r.output
    data = bytearray((tmp_path / "kf" / "keyframes.npz").read_bytes())
    data[len(data) // 2] ^= 0x01
    (tmp_path / "kf" / "keyframes.npz").write_bytes(bytes(data))
    r = CliRunner().invoke(edge_app, ["replay", str(tmp_path / "kf"), str(tiny["scene"]), "--align"])
    assert r.exit_code == 2 and "does not match the manifest" in r.output


def test_encoder_rank_exports_a_cheaper_graph_that_matches_its_torch_twin(tiny, tmp_path: Path) -> None:
    import onnx

    from acesplat.apps.cli import app
    from export.bundle_export import ExportOptions, export_bundle

    out = tmp_path / "lr"
    rep = export_bundle(tiny["map"], out, ExportOptions(size_hw=(64, 80), scene_path=tiny["scene"], encoder_rank=8))
    lr = rep.manifest["scr"]["encoder_lowrank"]
    assert lr["layer"] == "res2_conv3" and lr["rank"] == 8 and lr["macs_per_cell"] < lr["macs_per_cell_full"]
    assert 0.5 < lr["kept_variance"] <= 1.0 and lr["images"] == 12
    assert lr["frames"] > 0 and lr["coord_median"] >= 0.0  # what the rank costs against the exact encoder
    par = rep.manifest["checks"]["fp32_vs_torch"]  # the graph against the low-rank network it was traced from
    assert par["max_abs_diff_fraction"] < 1e-5
    g = onnx.load(str(out / "scr.onnx")).graph
    shapes = {tuple(t.dims) for t in g.initializer}
    assert any(s[0] == 8 and s[2:] == (3, 3) for s in shapes if len(s) == 4)  # the reduce layer: 8 channels out
    assert rep.manifest["scr"]["features"]["shape"][1] == 32  # the head and the initializer see the same width
    assert load_bundle(tiny["bundle"]).encoder_rank is None  # the default stays exact
    assert load_bundle(out).encoder_rank == 8
    from acesplat.apps.edge_cli import app as edge_app

    r = CliRunner().invoke(edge_app, ["replay", str(out), str(tiny["scene"]), "--json", str(tmp_path / "r.json")])
    assert r.exit_code == 0, r.output
    s = json.loads((tmp_path / "r.json").read_text())
    assert s["encoder_rank"] == 8 and s["localized"] == s["frames"] == 4  # run as any bundle (exact: 4 of 4 too)

    for rank, message in (("32", "between 1 and 31"), ("-1", "between 1 and 31")):
        r = CliRunner().invoke(
            app, ["export", str(tiny["map"]), "-o", str(tmp_path / "bad"), "--size", "64x80", "--encoder-rank", rank]
        )
        assert r.exit_code == 2 and message in r.output and "Traceback" not in r.output, r.output
    with pytest.raises(InputError, match="--encoder-rank fits on the map's training images"):
        export_bundle(
            tiny["map"], tmp_path / "b", ExportOptions(size_hw=(64, 80), scene_path=tmp_path / "gone", encoder_rank=8)
        )
    assert not (tmp_path / "bad").exists() and not (tmp_path / "b").exists()


def _map_on_encoder(tiny, encoder, tmp_path: Path, name: str) -> Path:
    """The tiny map with its head, pointed at ``encoder`` saved beside it as ``name``.pt."""
    import dataclasses

    import torch

    from acesplat.scr.encoders import EncoderIdentity
    from acesplat.scr.mapfile import load_map, save_map

    enc_path = tmp_path / f"{name}.pt"
    torch.save(encoder.state_dict(), enc_path)
    ident = EncoderIdentity(enc_path.name, file_sha256(enc_path), str(enc_path.resolve()))
    save_map(tmp_path / f"{name}.map", dataclasses.replace(load_map(tiny["map"]), encoder_identity=ident))
    return tmp_path / f"{name}.map"


def _refuses_encoder_rank(tiny, map_path: Path, tmp_path: Path, match: str) -> None:
    """``export --encoder-rank`` on ``map_path`` is a one-line InputError matching ``match`` and writes nothing."""
    from export.bundle_export import ExportOptions, export_bundle

    with pytest.raises(InputError, match=match):
        export_bundle(
            map_path, tmp_path / "b2", ExportOptions(size_hw=(64, 80), scene_path=tiny["scene"], encoder_rank=4)
        )
    assert not (tmp_path / "b2").exists()


def test_a_map_on_a_factorized_encoder_exports_as_it_is_and_refuses_a_second_factorization(tiny, tmp_path) -> None:
    import cv2

    from acesplat.core.scene import read_split
    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.lowrank import lowrank_encoder
    from export.bundle_export import ExportOptions, export_bundle

    enc, _ = load_encoder(tiny["encoder"])
    frames = [cv2.cvtColor(f.load_rgb(), cv2.COLOR_RGB2GRAY) for f in read_split(tiny["scene"], "train").frames]
    small, _ = lowrank_encoder(enc, frames, 8)
    map_path = _map_on_encoder(tiny, small, tmp_path, "encoder_rank8")
    rep = export_bundle(map_path, tmp_path / "b", ExportOptions(size_hw=(64, 80)))
    assert rep.manifest["checks"]["fp32_vs_torch"]["max_abs_diff_fraction"] < 1e-5  # the factorized network, traced
    _refuses_encoder_rank(tiny, map_path, tmp_path, "already factorized")


def test_a_map_on_a_separable_encoder_exports_to_int8_and_refuses_a_factorization(tiny, tmp_path) -> None:
    import torch

    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.network import Encoder, EncoderConfig
    from export.bundle_export import ExportOptions, export_bundle

    enc, _ = load_encoder(tiny["encoder"])
    torch.manual_seed(0)
    sep = Encoder(EncoderConfig(**{**enc.cfg.as_dict(), "separable": True}))
    sd = {k: v for k, v in enc.state_dict().items() if not k.startswith("res2_conv3.")}
    sd.update({k: v for k, v in sep.state_dict().items() if k.startswith("res2_conv3.")})
    sep.load_state_dict(sd)
    map_path = _map_on_encoder(tiny, sep, tmp_path, "encoder_separable")
    rep = export_bundle(map_path, tmp_path / "b", ExportOptions(size_hw=(64, 80), int8=True, scene_path=tiny["scene"]))
    checks = rep.manifest["checks"]
    assert checks["fp32_vs_torch"]["max_abs_diff_fraction"] < 1e-5  # the depthwise layer, traced
    assert (tmp_path / "b" / "scr.int8.onnx").is_file()
    _refuses_encoder_rank(tiny, map_path, tmp_path, "separable")


def test_int8_calibration_is_recorded_and_bad_values_are_one_line_errors(tiny, tmp_path: Path) -> None:
    from acesplat.apps.cli import app

    assert "percentile 99.999% calibration" in tiny["manifest"]["scr"]["int8_scheme"]
    for args, msg in (
        (["--int8-calibration", "kl"], "--int8-calibration must be one of minmax, percentile, entropy, got 'kl'"),
        (["--int8-percentile", "40"], "--int8-percentile must be above 50 and at most 100, got 40.0"),
    ):
        r = CliRunner().invoke(app, ["export", str(tiny["map"]), "-o", str(tmp_path / "b"), "--int8", *args])
        assert r.exit_code == 2, r.output
        assert r.stderr.count("\n") == 1 and msg in r.stderr
        assert not (tmp_path / "b").exists()


def test_percentile_ranges_are_inside_the_minmax_ranges_and_one_image_is_held_at_a_time(
    tiny, tmp_path: Path, capsys
) -> None:
    """Percentile clips each activation's rarest values, so no range is wider than MinMax's and most are narrower;
    the calibration reads its images one stride at a time, and says nothing on stdout (onnxruntime's calibrators
    print a line per image)."""
    import onnx
    from onnx import numpy_helper

    from export.quantize import _Images, quantize_int8

    fp32 = load_bundle(tiny["bundle"]).path("scr_fp32")
    g = np.random.default_rng(0)
    calib = [g.integers(0, 256, (64, 80), dtype=np.uint8) for _ in range(3)]
    reader = _Images(calib)
    reader.set_range(1, 2)
    first = reader.get_next()
    assert len(reader) == 3 and first is not None and reader.get_next() is None
    assert np.array_equal(next(iter(first.values()))[0, 0], calib[1])
    ranges = {}
    for method in ("minmax", "percentile"):
        out = quantize_int8(fp32, tmp_path / f"{method}.onnx", calib, method, percentile=99.0)
        graph = onnx.load(str(out)).graph
        inits = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
        ranges[method] = {
            n.input[0]: float(inits[n.input[1]]) * 255.0
            for n in graph.node
            if n.op_type == "QuantizeLinear" and inits[n.input[1]].ndim == 0
        }
    assert capsys.readouterr().out == ""
    common = ranges["minmax"].keys() & ranges["percentile"].keys()
    assert len(common) > 5
    assert all(ranges["percentile"][k] <= ranges["minmax"][k] * 1.001 for k in common)
    assert sum(ranges["percentile"][k] < ranges["minmax"][k] * 0.98 for k in common) > len(common) // 2


def test_int8_refuses_a_split_that_leaves_nothing_to_quantize(tiny, tmp_path: Path) -> None:
    from export.quantize import quantize_int8

    gray = np.zeros((64, 80), np.uint8)
    with pytest.raises(ValueError, match="no convolution left to quantize"):
        quantize_int8(Path(tiny["bundle"]) / "scr.onnx", tmp_path / "q.onnx", [gray], float_convs=10, float_lead=20)
    assert not (tmp_path / "q.onnx").exists()
