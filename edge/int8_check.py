"""INT8 verified where it runs: the bundle's stored frames through FP32 and INT8 on this CPU, compared with the
deviation the export measured on its own machine (``checks.int8_vs_fp32`` of the manifest).

INT8 kernels differ by CPU (onnxruntime's U8S8 products can saturate on x86 without VNNI), so a model checked on the
export machine may deviate on the device. The check passes when every deviation on this CPU is at most
``tolerance`` times the export's plus a slack (``Int8CheckConfig``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from acesplat.core.bundle import MANIFEST_NAME, Bundle
from acesplat.core.check_frames import bundle_check_frames, deviation
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from edge.inference import ScrSession, SessionSettings, runtime_info


@dataclass
class Int8CheckConfig:
    """The on-device INT8 check's bound."""

    frames: int = knob(4, "Stored frames to run through FP32 and INT8 (at most what the bundle carries).")
    tolerance: float = knob(
        1.5, "INT8 passes when each deviation from FP32 on this CPU is at most this many times the export's, + slack."
    )
    slack: float = knob(0.01, "Allowance added to the coordinate and translation bounds (scene units, metres).")
    slack_deg: float = knob(0.1, "Allowance added to the rotation bound (degrees).")
    skip: bool = knob(False, "Run INT8 without the on-device check against FP32 (localize/replay --int8).")


CRITERIA = (
    ("coord_median", "coordinate median", "slack"),
    ("coord_p90", "coordinate p90", "slack"),
    ("pose_median_translation", "pose translation median", "slack"),
    ("pose_median_rotation_deg", "pose rotation median", "slack_deg"),
)
"""(figure, words, which slack): what the device's INT8-vs-FP32 deviation is bounded on."""


@dataclass
class Int8CheckReport:
    """The check's verdict and every number behind it (``as_dict`` is the --json report)."""

    passed: bool
    failures: list[str]
    device: dict
    """INT8 vs FP32 on this CPU (acesplat.core.check_frames.deviation)."""
    export: dict
    """The same figures on the export machine, from the manifest."""
    fp32_vs_export: dict
    """This CPU's FP32 coordinates against the FP32 coordinates stored at export."""
    bounds: dict
    inference_ms: dict
    runtime: dict
    frames: list[str] = field(default_factory=list)
    config: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """One line: verdict, the device's figures against their bounds, ISA and onnxruntime."""
        d = self.device
        isa = " ".join(self.runtime["cpu_isa"]) or "-"
        figures = ", ".join(
            f"{words} {_fmt(d.get(k), k)} (bound {_fmt(self.bounds.get(k), k)})" for k, words, _ in CRITERIA
        )
        return (
            f"INT8 check {'passed' if self.passed else 'FAILED'} on {len(self.frames)} frames "
            f"(ISA {isa}, onnxruntime {self.runtime['onnxruntime']}, provider {self.runtime['provider']}): {figures}"
        )


def _fmt(v: float | None, key: str) -> str:
    if v is None:
        return "-"
    return f"{v:.3f} deg" if key.endswith("_deg") else f"{100 * v:.2f} cm"


def bound_for(export_value: float | None, slack: float, config: Int8CheckConfig) -> float | None:
    """``tolerance`` x the export's figure + ``slack``; None when the export has no figure to bound against."""
    if export_value is None:
        return None
    return config.tolerance * float(export_value) + slack


def judge(device: dict, export: dict, config: Int8CheckConfig) -> tuple[dict, list[str]]:
    """The bounds (by figure) and the failures (one phrase each) of ``device`` figures against ``export``'s."""
    bounds, failures = {}, []
    for key, words, slack_name in CRITERIA:
        b = bound_for(export.get(key), getattr(config, slack_name), config)
        bounds[key] = b
        v = device.get(key)
        if b is None:
            continue
        if v is None or not np.isfinite(v) or v > b:
            failures.append(f"{words} {_fmt(v, key)} > {_fmt(b, key)} (export {_fmt(export.get(key), key)})")
    if int(device.get("pose_frames") or 0) < int(export.get("pose_frames") or 0):
        failures.append(
            f"poses from both models on {device.get('pose_frames')} of {device.get('frames')} frames "
            f"(export: {export.get('pose_frames')})"
        )
    return bounds, failures


def _median_ms(sess: ScrSession, gray: np.ndarray, runs: int = 3) -> float:
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        sess.run(gray)
        ts.append((time.perf_counter() - t0) * 1000.0)
    return float(np.median(ts))


def check_int8(
    bundle: Bundle,
    config: Int8CheckConfig | None = None,
    threads: int | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
) -> Int8CheckReport:
    """Run the bundle's check frames (the first ``config.frames``) through its FP32 and INT8 models on this CPU and
    judge the INT8 deviation against the export's; InputError when the bundle cannot be checked (no INT8 model, no
    check frames, no export figures)."""
    config = config or Int8CheckConfig()
    if config.frames <= 0:
        raise InputError(None, f"--frames must be positive, got {config.frames}")
    if config.tolerance < 1.0 or config.slack < 0 or config.slack_deg < 0:
        raise InputError(
            None,
            f"the INT8 check's tolerance must be at least 1 and its slacks non-negative, got {config.tolerance}, "
            f"{config.slack}, {config.slack_deg}",
        )
    export = (bundle.manifest.get("checks") or {}).get("int8_vs_fp32")
    frames = bundle_check_frames(bundle)
    if not isinstance(export, dict) or "coord_median" not in export:
        raise InputError(bundle.root / MANIFEST_NAME, "manifest has no export INT8-vs-FP32 figures; re-export it")
    n = min(config.frames, len(frames))
    fp32 = ScrSession(bundle.scr_model("fp32"), bundle.input_size, threads, provider)
    int8 = ScrSession(bundle.scr_model("int8"), bundle.input_size, threads, provider)
    intr = [frames.intrinsics(i) for i in range(n)]
    ref = [fp32.run(frames.gray[i]) for i in range(n)]
    q = [int8.run(frames.gray[i]) for i in range(n)]
    stride = bundle.output_stride
    if n != export.get("frames"):  # the manifest's figures are over all the frames: the export's on these n
        export = {**export, **deviation(list(frames.coords[:n]), list(frames.int8_coords[:n]), intr, stride)}
    device = deviation(ref, q, intr, stride)
    diff = np.concatenate([np.linalg.norm(r - frames.coords[i], axis=-1).ravel() for i, r in enumerate(ref)])
    fp32_vs_export = {"coord_median": float(np.median(diff)), "coord_max": float(np.max(diff))}
    bounds, failures = judge(device, export, config)
    return Int8CheckReport(
        passed=not failures,
        failures=failures,
        device=device,
        export=export,
        fp32_vs_export=fp32_vs_export,
        bounds=bounds,
        inference_ms={"fp32": _median_ms(fp32, frames.gray[0]), "int8": _median_ms(int8, frames.gray[0])},
        runtime=runtime_info(provider),
        frames=frames.names[:n],
        config=asdict(config),
    )


def require_int8(
    bundle: Bundle,
    config: Int8CheckConfig | None = None,
    threads: int | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
) -> Int8CheckReport | None:
    """The check before an INT8 run: None with ``config.skip``; the report when INT8 passes; InputError in one line
    (naming the INT8 model, the first failure, ISA and onnxruntime) when it does not."""
    config = config or Int8CheckConfig()
    if config.skip:
        return None
    rep = check_int8(bundle, config, threads, provider)
    if not rep.passed:
        isa = " ".join(rep.runtime["cpu_isa"]) or "-"
        raise InputError(
            bundle.scr_model("int8"),
            f"INT8 deviates from FP32 on this CPU (ISA {isa}, onnxruntime {rep.runtime['onnxruntime']}): "
            f"{rep.failures[0]}; run FP32, re-export, or pass --skip-int8-check",
        )
    return rep
