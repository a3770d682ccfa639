"""Encoder pretraining with two gloo ranks: same weights on both, world size in the provenance, resumes the schedule."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import torch

from acesplat.scr import encoders
from acesplat.scr.pretrain import install_default

ROOT = Path(__file__).resolve().parents[1]

WORKER = """
import json, sys
import torch
from acesplat.scr.network import EncoderConfig
from acesplat.scr.pretrain import PretrainConfig, distributed_from_env, pretrain

runs, dump = json.loads(sys.argv[1]), sys.argv[2]
torch.set_num_threads(1)
tiny = EncoderConfig(c1=4, c2=8, c3=8, c4=16, res2=16, out=16)
results = []
with distributed_from_env("cpu") as (ddp, device):
    for out, steps, max_steps in runs:  # each call rebuilds everything from the checkpoint, as a new run would
        cfg = PretrainConfig(scenes=2, frames_per_scene=8, image_hw=(136, 168), steps=steps, pairs=2, encoder=tiny)
        lrs = []
        progress = lambda phase, f, info: lrs.append([info["step"], info["lr"]]) if phase == "train" else None
        s = pretrain(out, cfg, 2.0, progress, "worker", device, max_steps)
        results.append({"summary": s, "lrs": lrs})
with open(f"{dump}.{ddp.rank}.json", "w") as f:
    json.dump({"rank": ddp.rank, "results": results}, f)
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    env.update(PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MASTER_ADDR="127.0.0.1", MASTER_PORT=str(_free_port()))
    return env


def _run_two_ranks(runs: list[tuple[str, int, int | None]], dump: Path) -> list[list[dict]]:
    """Two gloo ranks running ``runs`` (out folder, steps, max_steps) one after the other; each rank's results."""
    env = _env()
    args = [sys.executable, "-c", WORKER, json.dumps(runs), str(dump)]
    procs = [
        subprocess.Popen(args, cwd=ROOT, env={**env, "RANK": str(r), "WORLD_SIZE": "2", "LOCAL_RANK": str(r)})
        for r in range(2)
    ]
    for p in procs:
        assert p.wait(timeout=240) == 0
    dumps = [json.loads(Path(f"{dump}.{r}.json").read_text()) for r in range(2)]
    assert [d["rank"] for d in dumps] == [0, 1]
    return [d["results"] for d in dumps]


def test_two_ranks_agree_record_world_size_and_resume_the_schedule(tmp_path, monkeypatch) -> None:
    whole, split = str(tmp_path / "whole"), str(tmp_path / "split")
    # An uninterrupted run of 4 steps, and the same schedule interrupted after one step and resumed.
    rank0, rank1 = _run_two_ranks([(whole, 4, None), (split, 4, 1), (split, 4, None)], tmp_path / "dump")
    for r0, r1 in zip(rank0, rank1, strict=True):  # identical weights on both ranks after every call
        assert r0["summary"]["weights_sha256"] == r1["summary"]["weights_sha256"]
        assert r0["summary"]["step"] == r1["summary"]["step"]
        assert r1["lrs"] == []  # only rank 0 reports progress
    uninterrupted, first, resumed = rank0

    assert uninterrupted["summary"]["step"] == 4 and uninterrupted["summary"]["finished"]
    saved = json.loads((tmp_path / "whole" / "pretrain_summary.json").read_text())
    assert saved["world_size"] == 2 and saved["backend"] == "gloo" and saved["global_batch_pairs"] == 4
    assert saved["sessions"][0]["world_size"] == 2 and saved["sessions"][0]["backend"] == "gloo"
    monkeypatch.setattr(encoders, "DEFAULT_ENCODER", tmp_path / "weights" / "encoder_default.pt")
    provenance = json.loads(install_default(whole, "install").with_suffix(".json").read_text())
    assert provenance["world_size"] == 2 and provenance["backend"] == "gloo"

    assert first["summary"]["step"] == 1 and not first["summary"]["finished"]
    assert resumed["summary"]["finished"] and resumed["summary"]["step"] == 4
    ck = torch.load(tmp_path / "split" / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert ck["step"] == 4
    assert [(s["start_step"], s["end_step"], s["world_size"]) for s in resumed["summary"]["sessions"]] == [
        (0, 1, 2),
        (1, 4, 2),
    ]
    assert [s for s, _ in first["lrs"] + resumed["lrs"]] == [1, 2, 3, 4]
    assert first["lrs"] + resumed["lrs"] == uninterrupted["lrs"]
    assert len({lr for _, lr in uninterrupted["lrs"]}) == 4  # a restarted schedule would repeat the first rate


def test_torchrun_runs_the_cli_on_two_cpu_ranks(tmp_path) -> None:
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", "-m"]
    cmd += ["acesplat.apps.cli", "pretrain-encoder", str(out), "--steps", "1", "--scenes", "2", "--frames", "8"]
    cmd += ["--size", "136x168", "--pairs", "1", "--device", "cpu", "--threads", "1"]
    env = {k: v for k, v in _env().items() if not k.startswith("MASTER_")}
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    saved = json.loads((out / "pretrain_summary.json").read_text())
    assert saved["world_size"] == 2 and saved["backend"] == "gloo" and saved["step"] == 1
    assert (out / "encoder.pt").is_file()
