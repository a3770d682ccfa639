"""Encoder pretraining resumes from its checkpoint and keeps every session's provenance."""

from __future__ import annotations

import torch

from acesplat.scr.network import EncoderConfig
from acesplat.scr.pretrain import PretrainConfig, pretrain

TINY = EncoderConfig(c1=4, c2=8, c3=8, c4=16, res2=16, out=16)


def test_pretraining_resumes_and_records_each_session(tmp_path) -> None:
    torch.manual_seed(0)
    cfg = PretrainConfig(scenes=1, frames_per_scene=8, image_hw=(136, 168), steps=3, encoder=TINY)
    first = pretrain(tmp_path, cfg, minutes=2.0, command="first")
    assert first["finished"] and first["step"] == 3
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
