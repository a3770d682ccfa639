"""Encoder pretraining resumes from its checkpoint and keeps every session's provenance."""

from __future__ import annotations

import json

import pytest
import torch

from acesplat.core.errors import InputError
from acesplat.scr import encoders
from acesplat.scr.network import EncoderConfig
from acesplat.scr.pretrain import Distributed, PretrainConfig, distributed_from_env, install_default, pretrain

TINY = EncoderConfig(c1=4, c2=8, c3=8, c4=16, res2=16, out=16)


def test_pretraining_resumes_and_records_each_session(tmp_path, monkeypatch) -> None:
    torch.manual_seed(0)
    cfg = PretrainConfig(scenes=1, frames_per_scene=8, image_hw=(136, 168), steps=3, encoder=TINY)
    first = pretrain(tmp_path, cfg, minutes=2.0, command="first")
    assert first["finished"] and first["step"] == 3
    assert first["world_size"] == 1 and first["backend"] is None and first["sessions"][0]["world_size"] == 1
    cfg.steps = 5  # a later session extends the schedule
    second = pretrain(tmp_path, cfg, minutes=2.0, command="second")
    assert second["finished"] and second["step"] == 5
    sessions = second["sessions"]
    assert [(s["command"], s["start_step"], s["end_step"], s["steps_planned"]) for s in sessions] == [
        ("first", 0, 3, 3),
        ("second", 3, 5, 5),
    ]
    ck = torch.load(tmp_path / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert ck["step"] == 5 and len(ck["sessions"]) == 2
    third = pretrain(tmp_path, cfg, minutes=2.0, command="third --install")  # finished: trains nothing
    assert third["step"] == 5 and third["sessions"] == sessions
    ck = torch.load(tmp_path / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert len(ck["sessions"]) == 2
    assert (tmp_path / "encoder.pt").is_file()
    monkeypatch.setattr(encoders, "DEFAULT_ENCODER", tmp_path / "weights" / "encoder_default.pt")
    provenance = json.loads(install_default(tmp_path, "install").with_suffix(".json").read_text())
    assert provenance["world_size"] == 1 and provenance["backend"] is None and provenance["steps"] == 5


def test_without_torchrun_variables_there_is_no_process_group(monkeypatch) -> None:
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(k, raising=False)
    with distributed_from_env("cpu") as (ddp, device):
        assert ddp == Distributed() and device == "cpu" and not torch.distributed.is_initialized()
    monkeypatch.setenv("WORLD_SIZE", "1")  # torchrun --nproc_per_node 1: a plain run too
    monkeypatch.setenv("RANK", "0")
    with distributed_from_env("cpu") as (ddp, _):
        assert ddp.world_size == 1 and not torch.distributed.is_initialized()
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "2")
    with pytest.raises(InputError, match="RANK"), distributed_from_env("cpu"):
        pass


def test_pair_gap_is_a_knob_and_a_bad_one_is_refused(tmp_path) -> None:
    from typer.testing import CliRunner

    from acesplat.apps.cli import app
    from acesplat.scr.pretrain import PAIR_MAX_GAP, PretrainConfig

    assert PretrainConfig().max_gap == PAIR_MAX_GAP
    with pytest.raises(ValueError, match="max_gap must be >= 1"):
        PretrainConfig(max_gap=0)
    r = CliRunner().invoke(app, ["pretrain-encoder", str(tmp_path / "run"), "--max-gap", "0"])
    assert r.exit_code == 2 and r.stderr.count("\n") == 1 and "--max-gap" in r.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("last", [{"rank": 6}, {"separable": True}])
def test_a_factorized_or_separable_init_encoder_is_pretrained_as_built_and_resumed_without_it(tmp_path, last) -> None:
    from acesplat.scr.network import Encoder, FactorizedConv2d, SeparableConv2d

    torch.manual_seed(1)
    built = EncoderConfig(c1=4, c2=8, c3=8, c4=16, res2=16, out=16, **last)
    enc = Encoder(built)
    init = tmp_path / "init.pt"
    torch.save(enc.state_dict(), init)
    cfg = PretrainConfig(
        scenes=1, frames_per_scene=8, image_hw=(136, 168), steps=2, encoder=TINY, init_encoder=str(init)
    )
    first = pretrain(tmp_path / "run", cfg, minutes=2.0, command="first")
    assert first["finished"] and first["config"]["encoder"] == built.as_dict()
    cfg = PretrainConfig(scenes=1, frames_per_scene=8, image_hw=(136, 168), steps=3, encoder=TINY)  # no init file
    second = pretrain(tmp_path / "run", cfg, minutes=2.0, command="second")
    assert second["finished"] and second["step"] == 3 and second["config"]["encoder"] == built.as_dict()
    trained, _ = encoders.load_encoder(tmp_path / "run" / "encoder.pt")
    assert trained.cfg == built
    assert isinstance(trained.res2_conv3, SeparableConv2d if built.separable else FactorizedConv2d)
