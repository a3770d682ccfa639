"""Execution providers (--provider): the name mapping, refusals in one line (unknown, not installed, silently fallen
back to the CPU), and the provider recorded beside the numbers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from typer.testing import CliRunner

from acesplat.apps.edge_cli import app
from acesplat.core.errors import InputError
from acesplat.core.machine import ISA_FLAGS, cpu_isa, machine_info
from edge.inference import (
    PROVIDERS,
    ScrSession,
    SessionSettings,
    check_provider,
    create_session,
    provider_list,
    runtime_info,
    session_options,
)

SIZE = (8, 8)
NAMES = "cpu, cuda, tensorrt, openvino, coreml"


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    """A real ONNX graph shaped like an SCR model: image (1, 1, 8, 8) -> coords (1, 3, 8, 8) (a 1x1 convolution)."""
    import onnx
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 1, *SIZE])
    y = helper.make_tensor_value_info("coords", TensorProto.FLOAT, [1, 3, *SIZE])
    w = helper.make_tensor("w", TensorProto.FLOAT, [3, 1, 1, 1], [1.0, 2.0, 3.0])
    graph = helper.make_graph([helper.make_node("Conv", ["image", "w"], ["coords"])], "tiny", [x], [y], [w])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    path = tmp_path_factory.mktemp("providers") / "tiny.onnx"
    onnx.save(model, str(path))
    return path


def fake_cuda(monkeypatch) -> list:
    """onnxruntime claims CUDA while the session it creates runs on the CPU only (what a CUDA build does when its
    libraries fail to load). The session is the real one on the real arguments: a call the real onnxruntime
    rejects fails here too. Returns the provider lists the sessions were asked for."""
    asked: list = []
    real_session = ort.InferenceSession

    class FallingBackSession(real_session):
        def __init__(self, path_or_bytes, sess_options=None, providers=None, provider_options=None, **kwargs):
            asked.append(list(providers or []))
            super().__init__(path_or_bytes, sess_options, ["CPUExecutionProvider"], provider_options, **kwargs)

    monkeypatch.setattr(ort, "InferenceSession", FallingBackSession)
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    return asked


# ----------------------------------------------------------------------------------- names and refusals
def test_names_map_to_onnxruntime_providers_with_the_cpu_behind() -> None:
    assert PROVIDERS == {
        "cpu": "CPUExecutionProvider",
        "cuda": "CUDAExecutionProvider",
        "tensorrt": "TensorrtExecutionProvider",
        "openvino": "OpenVINOExecutionProvider",
        "coreml": "CoreMLExecutionProvider",
    }
    assert provider_list("cpu") == ["CPUExecutionProvider"]
    for name, ep in PROVIDERS.items():
        if name != "cpu":
            assert provider_list(name) == [ep, "CPUExecutionProvider"]
    assert SessionSettings().provider == "cpu"


def test_unknown_name_is_refused_with_the_choices() -> None:
    with pytest.raises(InputError, match=f"--provider must be one of {NAMES}, got 'gpu'"):
        provider_list("gpu")
    with pytest.raises(InputError, match="one of"):
        check_provider("CUDAExecutionProvider")


def test_missing_provider_names_what_is_available_and_the_package() -> None:
    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this onnxruntime has CUDA")
    check_provider("cpu")
    with pytest.raises(InputError) as e:
        check_provider("cuda")
    msg = str(e.value)
    assert "\n" not in msg and "CUDAExecutionProvider" in msg and "onnxruntime-gpu" in msg
    assert "CPUExecutionProvider" in msg and ort.__version__ in msg


def test_cpu_session_runs_and_records_its_provider(tiny_model: Path) -> None:
    s = ScrSession(tiny_model, SIZE, threads=1)
    assert s.provider == "cpu" and s._sess.get_providers() == ["CPUExecutionProvider"]
    out = s.run(np.full(SIZE, 2, np.uint8))
    assert out.shape == (*SIZE, 3) and np.allclose(out[0, 0], [2.0, 4.0, 6.0])


def test_silent_fallback_is_refused(tiny_model: Path, monkeypatch) -> None:
    asked = fake_cuda(monkeypatch)
    with pytest.raises(InputError) as e:
        ScrSession(tiny_model, SIZE, threads=1, provider="cuda")
    assert asked == [["CUDAExecutionProvider", "CPUExecutionProvider"]]
    msg = str(e.value)
    assert "\n" not in msg and "fell back to CPUExecutionProvider" in msg and "CUDAExecutionProvider" in msg
    with pytest.raises(InputError, match="refusing to run the initializer"):
        create_session(tiny_model, session_options(1), "cuda", "the initializer")
    # the fake is the real session: what onnxruntime rejects, it rejects too
    with pytest.raises(InputError, match="cannot load"):
        create_session(tiny_model.with_name("missing.onnx"), session_options(1), "cuda")


# ----------------------------------------------------------------------------------- machine facts
def test_cpu_isa_flags_and_runtime_info() -> None:
    isa = cpu_isa()
    assert set(isa) <= {*ISA_FLAGS, "neon"}
    assert machine_info()["cpu_isa"] == isa
    assert runtime_info("cpu") == {"provider": "cpu", "onnxruntime": ort.__version__, "cpu_isa": isa}


def test_an_isa_limit_in_the_environment_is_recorded_and_turns_bfloat16_off(monkeypatch) -> None:
    from acesplat.core.machine import ISA_LIMIT_VARIABLES, bf16_units_usable, isa_limit, machine_line

    for k in ISA_LIMIT_VARIABLES:
        monkeypatch.delenv(k, raising=False)
    assert isa_limit() == {} and bf16_units_usable()
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx2")
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    assert isa_limit() == {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2"}
    assert machine_info()["isa_limit"] == isa_limit() and "ATEN_CPU_CAPABILITY=avx2" in machine_line()
    assert not bf16_units_usable()
    monkeypatch.delenv("ATEN_CPU_CAPABILITY")
    assert not bf16_units_usable()  # oneDNN alone capped at AVX2 has no bfloat16 kernels either
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX512_CORE_AMX")
    assert bf16_units_usable()


# ----------------------------------------------------------------------------------- the commands
def _cli(tiny, command: str, out: Path, *extra: str) -> list[str]:
    b = str(tiny["bundle"])
    args = {
        "localize": ["localize", b, "--source", f"replay:{tiny['scene']}/test", "--json-lines", str(out / "l.jsonl")],
        "replay": ["replay", b, str(tiny["scene"])],
        "profile": ["profile", b, "--frames", "2", "--warmup", "1"],
    }[command]
    return [*args, "--threads", "1", "--json", str(out / "s.json"), *extra]


@pytest.mark.parametrize("command", ["localize", "replay", "profile"])
def test_cli_refuses_a_provider_not_installed_and_writes_nothing(tiny, tmp_path: Path, command: str) -> None:
    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this onnxruntime has CUDA")
    r = CliRunner().invoke(app, _cli(tiny, command, tmp_path, "--provider", "cuda"))
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "onnxruntime-gpu" in lines[0], r.output
    assert list(tmp_path.iterdir()) == []


def test_cli_refuses_an_unknown_provider(tiny, tmp_path: Path) -> None:
    r = CliRunner().invoke(app, _cli(tiny, "replay", tmp_path, "--provider", "gpu"))
    assert r.exit_code == 2 and NAMES in r.output and list(tmp_path.iterdir()) == []


def test_cli_refuses_a_silent_fallback(tiny, tmp_path: Path, monkeypatch) -> None:
    asked = fake_cuda(monkeypatch)
    r = CliRunner().invoke(app, _cli(tiny, "replay", tmp_path, "--provider", "cuda"))
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "fell back" in lines[0], r.output
    assert asked and asked[0][0] == "CUDAExecutionProvider"
    assert list(tmp_path.iterdir()) == []


def test_replay_json_records_provider_and_onnxruntime(tiny, tmp_path: Path) -> None:
    r = CliRunner().invoke(app, _cli(tiny, "replay", tmp_path))
    assert r.exit_code == 0, r.output
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["provider"] == "cpu" and s["onnxruntime"] == ort.__version__ and s["cpu_isa"] == cpu_isa()
    assert s["frames"] == 4 and "timing_ms" in s


def test_profile_header_records_provider_and_onnxruntime(tiny, tmp_path: Path) -> None:
    r = CliRunner().invoke(app, _cli(tiny, "profile", tmp_path, "--provider", "cpu"))
    assert r.exit_code == 0, r.output
    h = json.loads((tmp_path / "s.json").read_text())["header"]
    assert h["provider"] == "cpu" and h["onnxruntime"] == ort.__version__ and h["cpu_isa"] == cpu_isa()
    assert "provider: cpu" in r.output


def test_localize_start_line_and_summary_record_provider(tiny, tmp_path: Path) -> None:
    r = CliRunner().invoke(app, [*_cli(tiny, "localize", tmp_path), "--frames", "2", "--quiet"])
    assert r.exit_code == 0, r.output
    assert f"provider cpu, onnxruntime {ort.__version__}" in r.output
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["provider"] == "cpu" and s["onnxruntime"] == ort.__version__ and s["frames"] == 2
