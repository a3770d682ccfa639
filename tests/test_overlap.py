"""How the edge loop runs: overlapped (edge.loop, LoopSettings.overlap: frame n+1 prepared while frame n is solved,
with the sequential loop's poses, order, counts and faults), onnxruntime's spinning (SessionSettings.spinning), and
the pose rate the firmware bridge reports."""

from __future__ import annotations

import json
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.apps.edge_cli import app
from acesplat.core.bundle import load_bundle
from acesplat.core.errors import InputError
from acesplat.core.pose import TrackingState
from acesplat.core.scene import read_split
from edge.loop import overlap_threads, run_loop
from edge.runtime import EdgeLocalizer, FrameOutcome
from edge.sources import ReplaySource, SourceFrame
from edge.tracking import Plan, Tracker, TrackingConfig
from tests.test_tracking import _sequence


def _run(loc: EdgeLocalizer, folder: Path, overlap: bool) -> list[FrameOutcome]:
    outs: list[FrameOutcome] = []
    stats = run_loop(ReplaySource(folder), loc, outs.append, overlap=overlap)
    assert stats.overlap == overlap and stats.frames == len(outs)
    return outs


def _same_outcomes(a: list[FrameOutcome], b: list[FrameOutcome]) -> None:
    assert [o.name for o in a] == [o.name for o in b]
    assert [o.mode for o in a] == [o.mode for o in b]
    assert [o.record.state for o in a] == [o.record.state for o in b]
    for x, y in zip(a, b, strict=True):
        assert x.record.inliers == y.record.inliers
        np.testing.assert_allclose(x.record.T_c2w, y.record.T_c2w, atol=1e-9, equal_nan=True)


def test_overlapped_replay_gives_the_sequential_poses_in_order(tiny) -> None:
    """Frames alone (no tracking): every frame, in order, with exactly the poses of the sequential loop."""
    b = load_bundle(tiny["bundle"])
    folder = Path(tiny["scene"]) / "test"
    seq = _run(EdgeLocalizer(b, "fp32", 1), folder, overlap=False)
    ovl = _run(EdgeLocalizer(b, "fp32", 1), folder, overlap=True)
    assert len(seq) == 4
    _same_outcomes(seq, ovl)
    assert all(o.times_ms["inference"] > 0 for o in ovl)


@pytest.fixture
def tiny_preset(monkeypatch) -> TrackingConfig:
    from acesplat.align.flow_pnp import TRACK_ALIGN
    from edge import tracking

    monkeypatch.setitem(tracking.ALIGN_PRESETS, "tiny", replace(TRACK_ALIGN, sample_step_px=1, min_points=50))
    return TrackingConfig(preset="tiny", reanchor_every=3)


def test_overlapped_tracking_plans_like_the_sequential_loop(tiny, tiny_preset, tmp_path: Path) -> None:
    """A camera holding each view for four frames, a black frame mid-run: the same modes (tracked, re-anchors,
    the fallback after the black frame), states and poses as the sequential loop; frames the pipeline expected to
    track skip the network as they would without it (after a frame that fell back, the guess can be wrong)."""
    b = load_bundle(tiny["bundle"])
    folder = _sequence(Path(tiny["scene"]), tmp_path / "seq" / "test", repeats=4, blank=6)
    seq = _run(EdgeLocalizer(b, "fp32", 1, tracking=tiny_preset), folder, overlap=False)
    ovl = _run(EdgeLocalizer(b, "fp32", 1, tracking=tiny_preset), folder, overlap=True)
    _same_outcomes(seq, ovl)
    modes = [o.mode for o in ovl]
    assert modes.count("tracked") >= 6 and modes.count("reanchor") >= 2, modes
    assert ovl[6].record.state == TrackingState.LOST and ovl[6].fallback is not None
    for prev, o in zip(ovl, ovl[1:]):
        if o.mode == "tracked" and prev.fallback is None:  # the frame before went as planned: nothing inferred ahead
            assert o.times_ms["inference"] == 0.0
        elif o.mode != "tracked":
            assert o.times_ms["inference"] > 0


def test_plan_after_is_the_plan_the_next_frame_gets_when_this_one_goes_as_planned() -> None:
    """Brute force over a tracked / re-anchored path: after each frame is tracked or solved as its plan says,
    ``plan()`` gives the mode ``plan_after`` announced."""
    rng = np.random.default_rng(0)
    for every in (1, 2, 3, 10):
        tr = Tracker(TrackingConfig(reanchor_every=every))
        pose = np.eye(4)
        for _ in range(40):
            plan = tr.plan()
            expected = tr.plan_after(plan)
            pose = pose.copy()
            pose[:3, 3] += rng.normal(0, 0.005, 3)
            if plan.mode == "track":
                tr.tracked(pose)
            else:
                tr.solved(pose, plan)
            assert tr.plan().mode == expected.mode, (every, plan.mode)
    assert Tracker(TrackingConfig(enabled=False)).plan_after(Plan("scr")).mode == "scr"


class _Live:
    """A camera faster than the localizer: frames every 2 ms, timestamps increasing."""

    live = True
    description = "fast camera"

    def __init__(self, rgb: np.ndarray, intrinsics, n: int = 400, intrinsics_from: int | None = None) -> None:
        self.rgb, self.intrinsics, self.n, self.i = rgb, intrinsics, n, 0
        self.intrinsics_from = intrinsics_from

    def read(self):
        time.sleep(0.002)
        self.i += 1
        if self.i > self.n:
            return None
        k = None if self.intrinsics_from is not None and self.i >= self.intrinsics_from else self.intrinsics
        return SourceFrame(self.rgb, time.monotonic(), k, self.i)

    def reconnect(self) -> None: ...

    def close(self) -> None: ...


def test_overlapped_live_source_keeps_the_latest_frame_and_counts_drops(tiny) -> None:
    f0 = read_split(tiny["scene"], "test").frames[0]
    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", 1)
    outs: list[FrameOutcome] = []

    def slow(o: FrameOutcome) -> None:
        outs.append(o)
        time.sleep(0.03)

    stats = run_loop(_Live(f0.load_rgb(), f0.intrinsics), loc, slow, max_frames=5, overlap=True)
    ids = [o.record.frame_id for o in outs]
    assert stats.frames == 5 and stats.dropped > 5
    assert ids == sorted(ids) and len(set(ids)) == 5
    assert not any(t.name == "prepare" and t.is_alive() for t in threading.enumerate())


def test_an_error_while_preparing_reaches_the_caller_and_the_threads_end(tiny) -> None:
    """A frame without intrinsics, met by the preparing thread: the same InputError as the sequential loop raises,
    on the caller's thread, after the frames before it were localized."""
    f0 = read_split(tiny["scene"], "test").frames[0]
    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", 1)
    outs: list[FrameOutcome] = []
    src = _Live(f0.load_rgb(), f0.intrinsics, n=50, intrinsics_from=4)
    src.live = False
    with pytest.raises(InputError, match="has no intrinsics"):
        run_loop(src, loc, outs.append, overlap=True)
    assert [o.record.frame_id for o in outs] == [1, 2, 3]
    assert not any(t.name == "prepare" and t.is_alive() for t in threading.enumerate())


def test_ctrl_c_while_overlapped_ends_cleanly(tiny, monkeypatch) -> None:
    import edge.runtime as rt

    calls = {"n": 0}
    real = rt.EdgeLocalizer.finish

    def interrupting(self, p):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(self, p)

    monkeypatch.setattr(rt.EdgeLocalizer, "finish", interrupting)
    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", 1)
    outs: list[FrameOutcome] = []
    stats = run_loop(ReplaySource(Path(tiny["scene"]) / "test"), loc, outs.append, overlap=True)
    assert stats.interrupted and stats.frames == 2 and len(outs) == 2
    assert not any(t.name == "prepare" and t.is_alive() for t in threading.enumerate())


def test_overlap_with_pacing_is_refused(tiny) -> None:
    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", 1, pace_ms=50.0)
    with pytest.raises(ValueError, match="pacing"):
        run_loop(ReplaySource(Path(tiny["scene"]) / "test"), loc, lambda o: None, overlap=True)


def test_replay_and_localize_commands_with_overlap(tiny, tmp_path: Path) -> None:
    """--overlap: the replay JSON records it, its threads (all cores but one) and the poses a second; with --refine
    it is refused in one line, exit 2; localize runs overlapped and reports it."""
    out, plain = tmp_path / "o.json", tmp_path / "p.json"
    runner = CliRunner()
    for flag, path in (("--overlap", out), ("--no-overlap", plain)):
        r = runner.invoke(
            app, ["replay", str(tiny["bundle"]), str(tiny["scene"]), "--no-tracking", flag, "--json", str(path)]
        )
        assert r.exit_code == 0, r.output
    s, p = json.loads(out.read_text()), json.loads(plain.read_text())
    assert s["overlap"] is True and p["overlap"] is False
    assert s["threads"] == overlap_threads() and s["poses_per_s"] > 0
    assert (s["frames"], s["localized"], s["median_translation_m"]) == (
        p["frames"],
        p["localized"],
        p["median_translation_m"],
    )

    r = runner.invoke(app, ["replay", str(tiny["bundle"]), str(tiny["scene"]), "--overlap", "--refine"])
    assert r.exit_code == 2 and "--overlap cannot run with --refine" in r.output
    assert len(r.output.strip().splitlines()) == 1 and "Traceback" not in r.output

    summary = tmp_path / "l.json"
    r = runner.invoke(
        app,
        [
            "localize",
            str(tiny["bundle"]),
            "--source",
            f"replay:{tiny['scene']}/test",
            "--overlap",
            "--quiet",
            "--json",
            str(summary),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "overlapped" in r.output
    ls = json.loads(summary.read_text())
    assert ls["overlap"] is True and ls["frames"] == 4


def test_the_bridge_reports_the_measured_pose_rate_not_one_over_the_latency(tiny) -> None:
    """With --overlap a pose's latency exceeds the time between poses: the status the microcontroller gets carries
    the rate measured between frames (the real sink on pyserial's loop:// port)."""
    from acesplat.apps.edge_cmd import BridgeTap
    from firmware_bridge.sink import open_sink

    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", 1)
    f0 = read_split(tiny["scene"], "test").frames[0]
    out = loc.localize(SourceFrame(f0.load_rgb(), 1.0, f0.intrinsics, 0))
    out.times_ms["total"] = 200.0  # a pose 200 ms old ...
    tap = BridgeTap(open_sink("loop://"))
    try:
        for _ in range(4):  # ... arriving every 20 ms
            tap.on_frame(out)
            time.sleep(0.02)
        status = dict(tap.sink._status)
    finally:
        tap.close()
    assert status["latency_ms"] == 200.0
    assert 20.0 < status["fps"] < 55.0  # about 50 a second (sleep plus the call), not 1000 / 200 = 5


def test_onnxruntime_threads_sleep_between_operators_unless_asked_and_runs_record_it(tiny, tmp_path: Path) -> None:
    """SessionSettings.spinning (on by default, bench/pipeline.md): the session's config, the localizer's session
    and the replay JSON all say which it was; --no-spinning turns it off."""
    from edge.inference import SessionSettings, session_options

    assert SessionSettings().spinning is True
    assert session_options(1).get_session_config_entry("session.intra_op.allow_spinning") == "1"
    assert session_options(1, spinning=False).get_session_config_entry("session.intra_op.allow_spinning") == "0"
    b = load_bundle(tiny["bundle"])
    assert EdgeLocalizer(b, "fp32", 1).session.spinning is True
    assert EdgeLocalizer(b, "fp32", 1, spinning=False).session.spinning is False
    for flag, want in (("--spinning", True), ("--no-spinning", False)):
        out = tmp_path / f"{flag}.json"
        r = CliRunner().invoke(
            app, ["replay", str(tiny["bundle"]), str(tiny["scene"]), "--no-tracking", flag, "--json", str(out)]
        )
        assert r.exit_code == 0, r.output
        assert json.loads(out.read_text())["spinning"] is want


def test_overlap_is_on_for_a_live_source_while_tracking_unless_set(tiny, tmp_path: Path) -> None:
    """LoopSettings.overlap unset: on for a live source while tracking (the camera's rate, bench/tracking.md), off
    for files read in step, frames alone, or beside refinement; --overlap/--no-overlap decide when given."""
    from edge.loop import overlap_for

    assert overlap_for(None, live=True, tracking=True)
    assert not overlap_for(None, live=False, tracking=True)
    assert not overlap_for(None, live=True, tracking=False)
    assert not overlap_for(None, live=True, tracking=True, paced=True)
    assert overlap_for(True, live=False, tracking=False) and not overlap_for(False, live=True, tracking=True)

    live = tmp_path / "live"
    live.mkdir()
    src = Path(tiny["scene"]) / "test"
    for sub in ("rgb", "poses", "calibration"):
        (live / sub).symlink_to(src / sub)
    n = len(list((src / "rgb").iterdir()))
    (live / "timestamps.txt").write_text("".join(f"{i / 30:.6f}\n" for i in range(n)))
    runs = {}
    for name, args in (
        ("live", ["--source", f"replay:{live}", "--realtime"]),
        ("live, frames alone", ["--source", f"replay:{live}", "--realtime", "--no-tracking"]),
        ("live, --no-overlap", ["--source", f"replay:{live}", "--realtime", "--no-overlap"]),
        ("files", ["--source", f"replay:{src}"]),
    ):
        out = tmp_path / f"{len(runs)}.json"
        r = CliRunner().invoke(app, ["localize", str(tiny["bundle"]), *args, "--quiet", "--json", str(out)])
        assert r.exit_code == 0, (name, r.output)
        runs[name] = json.loads(out.read_text())
    assert runs["live"]["overlap"] is True and runs["live"]["threads"] == overlap_threads()
    assert not any(runs[k]["overlap"] for k in ("live, frames alone", "live, --no-overlap", "files"))


@pytest.mark.parametrize("overlap", [False, True])
def test_a_camera_that_goes_away_is_reported_to_the_taps_while_it_is_gone(tiny, overlap: bool) -> None:
    """The 'disconnected' event reaches the taps (the firmware bridge reports LOST on it) while the camera is away,
    before the first frame after it comes back, in either loop."""
    import cv2

    from edge.calibration import CameraCalibration
    from edge.runtime import FrameTap
    from edge.sources import CameraSource
    from tests.test_edge_runtime import FakeCapture

    split = read_split(tiny["scene"], "test")
    frames = [cv2.cvtColor(f.load_rgb(), cv2.COLOR_RGB2BGR) for f in split.frames]
    script = {"reads": 0, "fail_at": 3, "opens": 0}

    class PacedCapture(FakeCapture):  # a camera's frame interval: the loop waits on an empty slot when it goes
        def read(self):
            time.sleep(0.03)
            return super().read()

    def opener(index: int):
        script["opens"] += 1
        cap = PacedCapture(frames, script)
        cap.opened = script["opens"] not in (2, 3, 4, 5)  # away for four reconnect attempts
        return cap

    class Log(FrameTap):
        def __init__(self) -> None:
            self.heard: dict[str, float] = {}  # event kind -> when the tap heard it
            self.events: dict[str, float] = {}  # event kind -> when it happened

        def on_event(self, event) -> None:
            self.heard.setdefault(event.kind, time.time())
            self.events.setdefault(event.kind, event.wall_time)

    calib = CameraCalibration(K=split.frames[0].intrinsics.K, size=(80, 64))
    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", 1)
    log = Log()
    loc.add_tap(log)
    stats = run_loop(
        CameraSource(0, calib, opener=opener), loc, lambda o: None, max_frames=4, backoff=(0.05, 0.1), overlap=overlap
    )
    assert stats.frames == 4 and stats.disconnects == 1
    assert log.heard["disconnected"] < log.events["reconnected"]  # reported while away, not when frames resume
