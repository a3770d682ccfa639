"""The SCR model in an onnxruntime session: grayscale uint8 (H, W) in, scene coordinates (h, w, 3) out,
and (bundle format 2) the encoder's features (C, h, w) for the splat initializer on request.

Every edge session is created by ``create_session`` on one execution provider (``SessionSettings.provider``):
an accelerator that is not installed, or a session that silently fell back to the CPU, is refused in one line.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from acesplat.core.bundle import SCR_COORDS_OUTPUT, SCR_FEATURES_OUTPUT
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.machine import cpu_isa

PROVIDERS = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
}
"""--provider name -> onnxruntime execution provider."""

PROVIDER_PACKAGES = {
    "cpu": "onnxruntime",
    "cuda": "onnxruntime-gpu",
    "tensorrt": "onnxruntime-gpu and TensorRT",
    "openvino": "onnxruntime-openvino",
    "coreml": "onnxruntime on macOS",
}
"""The pip package that brings each provider."""


@dataclass
class SessionSettings:
    """Where the edge's onnxruntime sessions run."""

    provider: str = knob("cpu", "Execution provider: cpu, cuda, tensorrt, openvino or coreml (nodes it lacks: CPU).")
    spinning: bool = knob(
        True, "onnxruntime's threads busy-wait between operators rather than sleep (either way: bench/pipeline.md)."
    )


def provider_list(name: str) -> list[str]:
    """onnxruntime's provider list for a --provider name: [that provider, CPUExecutionProvider] (the CPU takes
    the nodes an accelerator does not support), or just the CPU; InputError naming the choices for an unknown name."""
    if name not in PROVIDERS:
        raise InputError(None, f"--provider must be one of {', '.join(PROVIDERS)}, got {name!r}")
    return [PROVIDERS[name]] if name == "cpu" else [PROVIDERS[name], PROVIDERS["cpu"]]


def check_provider(name: str) -> None:
    """InputError in one line when ``name`` is unknown or its provider is not in this onnxruntime build."""
    wanted = provider_list(name)[0]
    available = ort.get_available_providers()
    if wanted not in available:
        raise InputError(
            None,
            f"--provider {name}: onnxruntime {ort.__version__} here has no {wanted} "
            f"(available: {', '.join(available)}); install {PROVIDER_PACKAGES[name]} to use it",
        )


def create_session(
    path: str | Path, sess_options: ort.SessionOptions, provider: str, what: str = "the model"
) -> ort.InferenceSession:
    """An onnxruntime session of the model at ``path`` on ``provider`` (a --provider name); InputError when the
    provider is missing, the model does not load, or the session did not get the provider it was asked for."""
    path = Path(path)
    check_provider(provider)
    providers = provider_list(provider)
    try:
        sess = ort.InferenceSession(str(path), sess_options=sess_options, providers=providers)
    except Exception as e:  # onnxruntime raises its own Fail/InvalidGraph types
        raise InputError(path, f"onnxruntime cannot load {what} ({str(e).splitlines()[0][:200]})") from None
    got = sess.get_providers()
    if not got or got[0] != providers[0]:
        raise InputError(
            path,
            f"--provider {provider}: the session fell back to {', '.join(got) or 'nothing'} instead of "
            f"{providers[0]} (its libraries did not load?); refusing to run {what} there",
        )
    return sess


def runtime_info(provider: str) -> dict:
    """What a run's numbers were measured on: provider (the --provider name), onnxruntime version, CPU ISA flags."""
    return {"provider": provider, "onnxruntime": ort.__version__, "cpu_isa": cpu_isa()}


def default_threads() -> int:
    """All cores this process may use (affinity-aware where the OS tells)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def session_options(
    threads: int | None = None, spinning: bool = knob_default(SessionSettings, "spinning")
) -> ort.SessionOptions:
    """Intra-op threads = cores (``threads`` if given); ``spinning``: the threads busy-wait between operators instead
    of sleeping (SessionSettings.spinning)."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads or default_threads()
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    so.log_severity_level = 3
    return so


class ScrSession:
    """One SCR model; checks the model's input shape against the bundle's input size.

    Outputs are found by name (a format 1 graph has only its coordinates, whatever their name: the first output).
    """

    def __init__(
        self,
        model_path: str | Path,
        input_size: tuple[int, int],
        threads: int | None = None,
        provider: str = knob_default(SessionSettings, "provider"),
        spinning: bool = knob_default(SessionSettings, "spinning"),
    ) -> None:
        self.path = Path(model_path)
        self.threads = threads or default_threads()
        self.provider = provider
        """The --provider name the session runs on."""
        self.spinning = spinning
        self._sess = create_session(self.path, session_options(self.threads, spinning), provider)
        inp = self._sess.get_inputs()[0]
        self._input = inp.name
        outputs = [o.name for o in self._sess.get_outputs()]
        self._output = SCR_COORDS_OUTPUT if SCR_COORDS_OUTPUT in outputs else outputs[0]
        self._features = SCR_FEATURES_OUTPUT if SCR_FEATURES_OUTPUT in outputs else None
        self.input_size = (int(input_size[0]), int(input_size[1]))
        shape = list(inp.shape)
        self.dynamic = len(shape) == 4 and not any(isinstance(d, int) for d in shape[2:])
        """Whether the graph takes any multiple of 8 in H and W (bundles exported since the dynamic graph)."""
        if len(shape) != 4 or not (self.dynamic or [shape[2], shape[3]] == list(self.input_size)):
            raise InputError(
                self.path, f"model input shape {shape} does not match the bundle input size {self.input_size}"
            )

    @property
    def has_features(self) -> bool:
        """Whether the graph also outputs the encoder's features (bundle format 2)."""
        return self._features is not None

    def accepts(self, size_hw: tuple[int, int]) -> bool:
        """Whether the graph runs at ``size_hw`` (H, W): its input size, or any multiple of 8 if it is dynamic."""
        if self.dynamic:
            return len(size_hw) == 2 and all(int(v) > 0 and int(v) % 8 == 0 for v in size_hw)
        return tuple(size_hw) == self.input_size

    def _feed(self, gray: np.ndarray) -> dict[str, np.ndarray]:
        if gray.ndim != 2 or not self.accepts(gray.shape):
            want = "(H, W) multiples of 8" if self.dynamic else f"{self.input_size} (H, W)"
            raise ValueError(f"image must be {want} grayscale, got {gray.shape}")
        return {self._input: np.ascontiguousarray(gray, dtype=np.float32)[None, None]}

    def run(self, gray: np.ndarray) -> np.ndarray:
        """Scene coordinates (h, w, 3) float32 for a grayscale image (H, W) the graph accepts (``accepts``)."""
        out = self._sess.run([self._output], self._feed(gray))[0]
        return np.ascontiguousarray(np.moveaxis(out[0], 0, -1))

    def run_with_features(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Coordinates (h, w, 3) and the encoder features (C, h, w) of one run (features None for a format 1 graph)."""
        if self._features is None:
            return self.run(gray), None
        coords, feats = self._sess.run([self._output, self._features], self._feed(gray))
        return np.ascontiguousarray(np.moveaxis(coords[0], 0, -1)), feats[0]
