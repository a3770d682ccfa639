"""Stage 1's recipe is fixed work (head steps and a full buffer), the same on every CPU; ``minutes`` is only a cap,
and a map it cuts short says so on the terminal and in its JSON."""

from __future__ import annotations

import json

import pytest
import torch
from typer.testing import CliRunner

from acesplat.core.config import knob_default
from acesplat.core.scene import read_split
from acesplat.scr.encoders import load_encoder
from acesplat.scr.mapping import MappingConfig, map_scene
from acesplat.synth import synthesize

SIZE = (64, 80)
TINY = dict(short_side=SIZE[0], batch_size=128, buffer_size=2000, samples_per_image=100, precision="fp32")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("recipe") / "scene"
    synthesize(out, seed=5, train_frames=12, test_frames=2, size=SIZE, supersample=1)
    return out


def test_the_default_recipe_is_a_step_count_with_no_clock() -> None:
    assert knob_default(MappingConfig, "minutes") is None
    assert knob_default(MappingConfig, "iterations") == 5000
    assert (knob_default(MappingConfig, "batch_size"), knob_default(MappingConfig, "buffer_passes")) == (2560, 20)


def test_uncapped_mapping_does_all_its_work(scene) -> None:
    enc, _ = load_encoder(None)
    torch.manual_seed(0)
    res = map_scene(read_split(scene, "train"), enc, MappingConfig(iterations=25, **TINY))
    assert (res.iterations, res.iterations_planned, res.buffer_features, res.cut_short) == (25, 25, 2000, False)


def test_a_cap_that_binds_cuts_the_map_short_and_says_so(scene) -> None:
    enc, _ = load_encoder(None)
    res = map_scene(read_split(scene, "train"), enc, MappingConfig(iterations=100_000, minutes=0.05, **TINY))
    assert res.cut_short and res.iterations < res.iterations_planned == 100_000
    assert res.seconds < 0.05 * 60 + 5.0  # the cap holds, with a margin for loading and the last step


def test_map_command_warns_and_flags_a_cut_short_map(scene, tmp_path) -> None:
    from acesplat.apps.cli import app

    out = tmp_path / "m.json"
    args = ["map", str(scene), "-o", str(tmp_path / "m.pt"), "--steps", "100000", "--minutes", "0.02"]
    r = CliRunner().invoke(app, [*args, "--precision", "fp32", "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "cut the recipe short" in r.output
    j = json.loads(out.read_text())
    assert j["cut_short"] is True and j["iterations"] < j["iterations_planned"] == 100_000
    assert j["precision"] == "fp32" and isinstance(j["cpu_isa"], list)


def test_auto_precision_is_float32_under_an_avx2_limit(monkeypatch) -> None:
    from acesplat.scr.mapping import use_bf16

    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx2")
    assert use_bf16("auto", "cpu") is False and use_bf16("bf16", "cpu") is True


def test_a_small_scene_stops_buffering_after_its_passes(scene) -> None:
    enc, _ = load_encoder(None)
    cfg = MappingConfig(iterations=2, **{**TINY, "buffer_size": 10**6, "buffer_passes": 2})
    res = map_scene(read_split(scene, "train"), enc, cfg)
    # 12 training images, 2 passes, each augmented 64 x 80 view giving at most its 8 x 10 cells
    assert 2 * 12 * 60 <= res.buffer_features <= 2 * 12 * 80 and not res.cut_short


def test_map_command_takes_batch_and_buffer_knobs_and_records_them(scene, tmp_path, monkeypatch) -> None:
    from acesplat.apps.cli import app

    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx2")
    out = tmp_path / "m.json"
    args = ["map", str(scene), "-o", str(tmp_path / "m.pt"), "--steps", "3", "--batch-size", "64"]
    r = CliRunner().invoke(app, [*args, "--buffer-size", "500", "--buffer-passes", "3", "--json", str(out)])
    assert r.exit_code == 0, r.output
    j = json.loads(out.read_text())
    assert (j["batch_size"], j["buffer_passes"], j["buffer_features"]) == (64, 3, 500)
    assert j["precision"] == "fp32" and j["isa_limit"]["ATEN_CPU_CAPABILITY"] == "avx2"


def test_map_command_refuses_a_non_positive_cap(scene, tmp_path) -> None:
    from acesplat.apps.cli import app

    r = CliRunner().invoke(app, ["map", str(scene), "-o", str(tmp_path / "m.pt"), "--minutes", "0"])
    assert r.exit_code == 2 and "--minutes" in r.output and "Traceback" not in r.output


def _map_cli(scene, tmp_path):
    from acesplat.apps.cli import app

    out = tmp_path / "m.pt"
    r = CliRunner().invoke(app, ["map", str(scene), "-o", str(out), "--steps", "5", "--precision", "fp32"])
    return r, out


def test_a_scene_with_two_training_images_is_refused(scene, tmp_path) -> None:
    import shutil

    small = tmp_path / "two"
    for sub in ("rgb", "poses", "calibration"):
        files = sorted((scene / "train" / sub).iterdir())[:2]
        (small / "train" / sub).mkdir(parents=True)
        for f in files:
            shutil.copy(f, small / "train" / sub / f.name)
    r, out = _map_cli(small, tmp_path)
    assert r.exit_code == 2, r.output
    assert "2 training image(s); mapping needs at least 3" in r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1
    assert not out.exists()


def test_training_images_without_overlap_are_refused(tmp_path) -> None:
    import numpy as np

    from acesplat.core.geometry import make_pose
    from acesplat.core.scene import write_frame

    rng = np.random.default_rng(0)
    K = np.array([[60.0, 0, 40], [0, 60.0, 32], [0, 0, 1]])
    noisy = tmp_path / "noise"
    for i in range(4):  # independent noise images, cameras turned away from each other: nothing matches
        rgb = rng.integers(0, 256, (64, 80, 3), dtype=np.uint8)
        a = np.radians(90.0 * i)
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        write_frame(noisy / "train", f"{i:04d}", rgb, make_pose(R, np.array([0.3 * i, 0, 0])), K)
    r, out = _map_cli(noisy, tmp_path)
    assert r.exit_code == 2, r.output
    assert "do not overlap" in r.output and str(noisy / "train") in r.output
    assert "Traceback" not in r.output
    assert not out.exists()
