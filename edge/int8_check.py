"""INT8 verified where it runs: the bundle's stored frames through FP32 and INT8 on this CPU, compared with the
deviation the export measured on its own machine (``checks.int8_vs_fp32`` of the manifest).

INT8 kernels differ by CPU (onnxruntime's U8S8 products can saturate on x86 without VNNI), so a model checked on the
export machine may deviate on the device. The check passes when every deviation on this CPU is at most
``tolerance`` times the export's plus a slack (``Int8CheckConfig``). A U8S8 graph also needs this CPU's U8S8 kernel
to be exact (``u8s8_probe_error``), and a graph other than the default needs to be about as close to FP32 as the
default is on this CPU: a saturating U8S8 graph can stay inside the export's bounds while it loses a third of its
coordinates' precision (bench/int8_format.md, "AVX2 emulated").
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from acesplat.core.bundle import INT8_PRECISIONS, MANIFEST_NAME, PRECISION_ROLES, ROLE_INT8_CHECK, Bundle
from acesplat.core.check_frames import CheckFrames, bundle_check_frames, deviation
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from edge.inference import ScrSession, SessionSettings, runtime_info, session_options

U8S8_PROBE = Path(__file__).with_name("u8s8_probe.onnx")
"""A U8 x S8 product whose int16 pair sums overflow, beside the same product in U8 x U8 (export/u8s8_probe.py)."""
U8S8_PROBE_INPUT = 255
"""The value fed in every element of the probe's input (export.u8s8_probe.PROBE_INPUT)."""


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
    other_tolerance: float = knob(
        1.2,
        "A graph other than the default passes only when its coordinate median and p90 on this CPU are at most this "
        "many times the default graph's, + slack (a saturating U8S8 graph loses 40% at p90: bench/int8_format.md).",
    )


INT8_MIN_GAIN = 0.1
"""A graph other than the default runs only when its inference is at least this much faster on this CPU."""

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
    precision: str = "int8"
    """The INT8 graph checked (acesplat.core.bundle.INT8_PRECISIONS)."""
    u8s8_probe_error: float | None = None
    """This CPU's U8S8 kernel on the saturation probe: relative error (0 = exact); None when not run (a graph that
    is not U8S8, or a provider other than cpu)."""

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """One line: verdict, the device's figures against their bounds, ISA and onnxruntime."""
        d = self.device
        isa = " ".join(self.runtime["cpu_isa"]) or "-"
        figures = ", ".join(
            f"{words} {_fmt(d.get(k), k)} (bound {_fmt(self.bounds.get(k), k)})" for k, words, _ in CRITERIA
        )
        name = "INT8" if self.precision == "int8" else f"INT8 ({self.precision})"
        return (
            f"{name} check {'passed' if self.passed else 'FAILED'} on {len(self.frames)} frames "
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


@functools.cache
def u8s8_probe_error(provider: str = "cpu") -> float | None:
    """Relative error of onnxruntime's U8S8 integer product on this CPU against the exact U8U8 one (0.0 where VNNI,
    AMX or a widening kernel runs it; about 0.4 where pair sums saturate, x86 without VNNI); None on a provider
    other than cpu, whose kernels the probe does not reach."""
    if provider != "cpu":
        return None
    sess = ort.InferenceSession(str(U8S8_PROBE), sess_options=session_options(1), providers=["CPUExecutionProvider"])
    inp = sess.get_inputs()[0]
    a = np.full(inp.shape, U8S8_PROBE_INPUT, dtype=np.uint8)
    y, exact = (o.astype(np.int64) for o in sess.run(["Y", "Y_exact"], {inp.name: a}))
    return float(np.abs(y - exact).max() / max(1, np.abs(exact).max()))


def is_u8s8(bundle: Bundle, precision: str) -> bool:
    """Whether the bundle's INT8 graph of ``precision`` multiplies uint8 by int8 (U8S8, or S8S8, which onnxruntime
    runs as U8S8 on x86): the manifest's scheme text, and the twin always."""
    if precision == "int8_vnni":
        return True
    scheme = str(bundle.manifest.get("scr", {}).get(f"{precision}_scheme", ""))
    return "U8S8" in scheme or "S8S8" in scheme


def int8_precisions(bundle: Bundle) -> list[str]:
    """The INT8 graphs the bundle carries, the default first (acesplat.core.bundle.INT8_PRECISIONS)."""
    return [p for p in INT8_PRECISIONS if bundle.has(PRECISION_ROLES[p])]


def _export_figures(bundle: Bundle, precision: str) -> dict:
    checks = bundle.manifest.get("checks") or {}
    export = checks.get("int8_vs_fp32" if precision == "int8" else f"{precision}_vs_fp32")
    if not isinstance(export, dict) or "coord_median" not in export:
        raise InputError(
            bundle.root / MANIFEST_NAME, f"manifest has no export {precision.upper()}-vs-FP32 figures; re-export it"
        )
    return export


def check_int8(
    bundle: Bundle,
    config: Int8CheckConfig | None = None,
    threads: int | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
    precisions: Sequence[str] = ("int8",),
) -> list[Int8CheckReport]:
    """Run the bundle's check frames (the first ``config.frames``) through its FP32 model and each INT8 graph of
    ``precisions`` on this CPU and judge each one's deviation against the export's; InputError when the bundle
    cannot be checked (no such INT8 model, no check frames, no export figures).

    A graph other than the default ('int8') is also held to the default's coordinate bounds: a U8S8 graph exported
    on a CPU where it saturates carries loose figures of its own."""
    config = config or Int8CheckConfig()
    if config.frames <= 0:
        raise InputError(None, f"--frames must be positive, got {config.frames}")
    if config.tolerance < 1.0 or config.other_tolerance < 1.0 or config.slack < 0 or config.slack_deg < 0:
        raise InputError(
            None,
            f"the INT8 check's tolerances must be at least 1 and its slacks non-negative, got {config.tolerance}, "
            f"{config.other_tolerance}, {config.slack}, {config.slack_deg}",
        )
    for p in precisions:  # every figure the verdict needs, before any model runs
        _export_figures(bundle, p)
    frames = bundle_check_frames(bundle)
    n = min(config.frames, len(frames))
    fp32 = ScrSession(bundle.scr_model("fp32"), bundle.input_size, threads, provider)
    ref = [fp32.run(frames.gray[i]) for i in range(n)]
    fp32_ms = _median_ms(fp32, frames.gray[0])
    diff = np.concatenate([np.linalg.norm(r - frames.coords[i], axis=-1).ravel() for i, r in enumerate(ref)])
    fp32_vs_export = {"coord_median": float(np.median(diff)), "coord_max": float(np.max(diff))}
    sessions = {p: ScrSession(bundle.scr_model(p), bundle.input_size, threads, provider) for p in precisions}
    coords = {p: [s.run(frames.gray[i]) for i in range(n)] for p, s in sessions.items()}
    probe = u8s8_probe_error(provider) if any(is_u8s8(bundle, p) for p in precisions) else None
    reports = []
    verdicts = judge_graphs(bundle, frames, ref, coords, config, probe)
    for precision, (device, export, bounds, failures) in verdicts.items():
        reports.append(
            Int8CheckReport(
                passed=not failures,
                failures=failures,
                device=device,
                export=export,
                fp32_vs_export=fp32_vs_export,
                bounds=bounds,
                inference_ms={"fp32": fp32_ms, "int8": _median_ms(sessions[precision], frames.gray[0])},
                runtime=runtime_info(provider),
                frames=frames.names[:n],
                config=asdict(config),
                precision=precision,
                u8s8_probe_error=probe if is_u8s8(bundle, precision) else None,
            )
        )
    return reports


def judge_graphs(
    bundle: Bundle,
    frames: CheckFrames,
    reference: list[np.ndarray],
    coords: dict[str, list[np.ndarray]],
    config: Int8CheckConfig | None = None,
    u8s8_error: float | None = None,
) -> dict[str, tuple[dict, dict, dict, list[str]]]:
    """The verdict on INT8 coordinate grids of the first ``len(reference)`` of the bundle's check ``frames``
    (acesplat.core.check_frames.bundle_check_frames): ``reference`` the FP32 grids (h, w, 3) and ``coords`` each
    INT8 precision's grids, computed on the CPU being judged; ``u8s8_error`` that CPU's ``u8s8_probe_error`` (None:
    not probed). Per precision: (device figures, export figures, bounds, failures); passed when failures is empty.

    Every graph is held to the export's figures (``judge``); a U8S8 graph also to an exact probe; a graph other than
    the default ('int8', which ``coords`` must then hold) also to the default's coordinate figures on this CPU."""
    config = config or Int8CheckConfig()
    n = len(reference)
    if not 0 < n <= len(frames) or any(len(c) != n for c in coords.values()):
        raise ValueError(f"need 1..{len(frames)} reference grids and as many per precision, got {n}")
    if "int8" not in coords and coords:
        raise ValueError("a graph other than the default is judged beside the default ('int8')")
    intr = [frames.intrinsics(i) for i in range(n)]
    stride = bundle.output_stride
    devices = {p: deviation(reference, grids, intr, stride) for p, grids in coords.items()}
    out = {}
    for precision in coords:
        export = _export_figures(bundle, precision)
        try:
            stored = frames.int8(precision)
        except ValueError:
            raise InputError(bundle.path(ROLE_INT8_CHECK), f"check frames carry no {precision} coordinates") from None
        if n != export.get("frames"):  # the manifest's figures are over all the frames: the export's on these n
            export = {**export, **deviation(list(frames.coords[:n]), list(stored[:n]), intr, stride)}
        device = devices[precision]
        bounds, failures = judge(device, export, config)
        if u8s8_error is not None and u8s8_error > 0.0 and is_u8s8(bundle, precision):
            failures.insert(
                0,
                f"this CPU's U8S8 products saturate (a probe product off by {100 * u8s8_error:.0f}%: x86 without "
                "VNNI), so a U8S8 graph loses precision here",
            )
        if precision != "int8":
            failures += _as_close_as_default(device, devices["int8"], config)
        out[precision] = (device, export, bounds, failures)
    return out


def _as_close_as_default(device: dict, default: dict, config: Int8CheckConfig) -> list[str]:
    """Failures of a non-default graph's coordinate figures against the default INT8 graph's on the same CPU."""
    out = []
    for key, words, slack in CRITERIA[:2]:
        b, v = config.other_tolerance * float(default[key]) + getattr(config, slack), device.get(key)
        if v is None or not np.isfinite(v) or v > b:
            out.append(f"{words} {_fmt(v, key)} > {_fmt(b, key)} ({config.other_tolerance:g} x the default graph's)")
    return out


def choose_int8(
    bundle: Bundle,
    config: Int8CheckConfig | None = None,
    threads: int | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
) -> tuple[str | None, list[Int8CheckReport]]:
    """Check every INT8 graph the bundle carries on this CPU; the precision to run (the fastest that passes, the
    default unless another is faster by ``INT8_MIN_GAIN``; None when none passes) and the reports, default first."""
    reports = check_int8(bundle, config, threads, provider, int8_precisions(bundle))
    passed = [r for r in reports if r.passed]
    if not passed:
        return None, reports
    chosen = passed[0]
    for r in passed[1:]:
        if r.inference_ms["int8"] < (1.0 - INT8_MIN_GAIN) * chosen.inference_ms["int8"]:
            chosen = r
    return chosen.precision, reports


def require_int8(
    bundle: Bundle,
    config: Int8CheckConfig | None = None,
    threads: int | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
) -> tuple[str, list[Int8CheckReport]]:
    """The check before an INT8 run: the INT8 precision to run and the reports (('int8', []) with ``config.skip``:
    the default graph, unverified); InputError in one line (naming the INT8 model, the default graph's first
    failure, ISA and onnxruntime) when no INT8 graph passes."""
    config = config or Int8CheckConfig()
    if config.skip:
        return "int8", []
    precision, reports = choose_int8(bundle, config, threads, provider)
    if precision is None:
        rep = reports[0]
        isa = " ".join(rep.runtime["cpu_isa"]) or "-"
        raise InputError(
            bundle.scr_model("int8"),
            f"INT8 deviates from FP32 on this CPU (ISA {isa}, onnxruntime {rep.runtime['onnxruntime']}): "
            f"{rep.failures[0]}; run FP32, re-export, or pass --skip-int8-check",
        )
    return precision, reports
