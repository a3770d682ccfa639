"""Tracking between frames: the state machine on synthetic poses, then the edge runtime on the tiny bundle."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.core.geometry import look_at, make_pose, pose_error, rodrigues_to_matrix
from edge.tracking import Plan, Tracker, TrackingConfig


def _trajectory(n: int, step_m: float = 0.02, step_deg: float = 0.5) -> list[np.ndarray]:
    """Camera-to-world poses moving at constant velocity (a screw motion) in the camera's own frame."""
    d = make_pose(rodrigues_to_matrix(np.radians([0.0, step_deg, 0.0])), np.array([step_m, 0.0, 0.0]))
    T = [look_at(np.array([0.0, -2.0, 1.0]), np.array([0.0, 0.0, 1.0]))]
    for _ in range(n - 1):
        T.append(T[-1] @ d)
    return T


def test_constant_velocity_prediction_is_exact_on_a_constant_velocity_path() -> None:
    tr = Tracker(TrackingConfig(reanchor_every=100))
    T = _trajectory(6)
    assert tr.plan() == Plan("scr") and tr.predict() is None
    assert not tr.solved(T[0], tr.plan())
    p = tr.plan()
    assert p.mode == "track" and np.allclose(p.prediction, T[0])  # one pose: no velocity yet
    tr.tracked(T[1])
    for k in range(2, 6):
        p = tr.plan()
        assert p.mode == "track" and p.moving
        dt, dr = pose_error(p.prediction, T[k])
        assert dt < 1e-12 and dr < 1e-6
        tr.tracked(T[k])


def test_velocity_is_per_camera_frame_across_dropped_frames() -> None:
    """Frames the loop dropped still advance the source's frame ids: the prediction for a frame k ids after the last
    pose is k steps of the velocity, and a velocity measured across a gap is divided by it; exact on a constant
    velocity path. Without ids, or with ids that do not increase, a step is a processed frame."""
    T = _trajectory(16, step_m=0.04, step_deg=4.0)
    tr = Tracker(TrackingConfig(reanchor_every=100, max_motion_m=10.0, max_motion_deg=90.0))
    tr.solved(T[0], tr.plan(0), 0)
    tr.tracked(T[1], 1)
    for k in (2, 4, 5):  # the next frame, and frames after two and three drops
        dt, dr = pose_error(tr.plan(k).prediction, T[k])
        assert dt < 1e-9 and dr < 1e-6, k
    tr.tracked(T[4], 4)  # a velocity measured across a gap of three frames ...
    dt, dr = pose_error(tr.plan(5).prediction, T[5])  # ... is one third of that motion per frame
    assert dt < 1e-9 and dr < 1e-6
    assert pose_error(tr.predict(), T[7])[0] < 1e-9  # no id: one processed frame (three camera frames here)
    assert pose_error(tr.predict(3), T[7])[0] < 1e-9  # an id that does not increase: the same
    # the motion to the frame decides 'too far': 4 cm a frame tracks, the same velocity five frames on does not
    cfg = TrackingConfig(max_motion_m=0.15, max_motion_deg=30.0, reanchor_every=100)
    tr = Tracker(cfg)
    tr.solved(T[0], tr.plan(10), 10)
    tr.tracked(T[1], 11)
    assert tr.plan(12).mode == "track" and tr.plan(16).reason == "too_far"
    # after a gap, SCR solves frame 15, the loop keeps up again: frame 16 is one step of the velocity, tracked
    tr.solved(T[5], tr.plan(15), 15)
    p = tr.plan(16)
    assert p.mode == "track" and pose_error(p.prediction, T[6])[0] < 1e-9


def test_reanchor_interval_and_reset_counting() -> None:
    cfg = TrackingConfig(reanchor_every=3, reset_m=0.05, reset_deg=2.0)
    tr = Tracker(cfg)
    T = _trajectory(12)
    modes = []
    for k in range(12):
        p = tr.plan()
        modes.append(p.mode)
        if p.mode == "track":
            tr.tracked(T[k])
        else:
            pose = T[k]
            if k == 8:  # this re-anchor lands 10 cm from the tracked prediction: a jump
                pose = T[k] @ make_pose(np.eye(3), np.array([0.1, 0.0, 0.0]))
            assert tr.solved(pose, p) == (k == 8)
    assert modes == [
        "scr",
        "track",
        "track",
        "track",
        "reanchor",
        "track",
        "track",
        "track",
        "reanchor",
        *["track"] * 3,
    ]
    assert tr.reset_counter == 1
    # a small disagreement at a re-anchor (1 cm, SCR's noise) is no reset
    assert not tr.solved(T[11] @ make_pose(np.eye(3), np.array([0.01, 0.0, 0.0])), Plan("reanchor", T[11]))
    assert tr.reset_counter == 1


def test_too_far_to_track_and_lost_fall_back_to_scr() -> None:
    cfg = TrackingConfig(max_motion_m=0.15)
    tr = Tracker(cfg)
    T = _trajectory(5, step_m=0.2)  # 20 cm a frame: beyond what is tracked
    tr.solved(T[0], tr.plan())
    p = tr.plan()
    assert p.mode == "track" and not p.moving  # no velocity yet: the alignment decides (and falls back)
    assert not tr.solved(T[1], Plan("reanchor", p.prediction))  # SCR's pose is 20 cm on: motion, not a jump
    p = tr.plan()
    assert p == Plan("scr", None, "too_far")
    assert not tr.solved(T[2], p) and tr.plan().reason == "too_far"  # still too fast: SCR until the motion slows
    tr.solved(T[2] @ make_pose(np.eye(3), np.array([0.01, 0.0, 0.0])), tr.plan())
    assert tr.plan().mode == "track"
    tr.solved(None, tr.plan())  # the gate refused SCR's pose: LOST
    assert tr.history == [] and tr.plan() == Plan("scr")
    assert Tracker(TrackingConfig(enabled=False)).plan() == Plan("scr")


def test_bad_tracking_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="reanchor_every"):
        TrackingConfig(reanchor_every=0)
    with pytest.raises(ValueError, match="max_motion_m"):
        TrackingConfig(max_motion_m=0.0)
    with pytest.raises(ValueError, match="preset"):
        TrackingConfig(preset="fast")


# ----------------------------------------------------------------------------------- the runtime on the tiny bundle
def _sequence(scene: Path, out: Path, repeats: int = 3, blank: int | None = None) -> Path:
    """A split whose frames are the tiny test views, each held for ``repeats`` frames (a camera that pauses), with
    frame ``blank`` replaced by a black image (a covered lens)."""
    import cv2

    src = scene / "test"
    names = sorted(p.stem for p in (src / "rgb").glob("*.png"))
    for sub in ("rgb", "poses", "calibration"):
        (out / sub).mkdir(parents=True)
    k = 0
    for name in names:
        for _ in range(repeats):
            shutil.copy(src / "rgb" / f"{name}.png", out / "rgb" / f"{k:04d}.png")
            shutil.copy(src / "poses" / f"{name}.txt", out / "poses" / f"{k:04d}.txt")
            shutil.copy(src / "calibration" / f"{name}.txt", out / "calibration" / f"{k:04d}.txt")
            if k == blank:
                img = cv2.imread(str(out / "rgb" / f"{k:04d}.png"))
                cv2.imwrite(str(out / "rgb" / f"{k:04d}.png"), np.zeros_like(img))
            k += 1
    return out


@pytest.fixture
def tiny_preset(monkeypatch):
    """TRACK_ALIGN at the tiny bundle's 64x80 input: every pixel sampled (the default grid gives too few pairs)."""
    from dataclasses import replace

    from acesplat.align.flow_pnp import TRACK_ALIGN
    from edge import tracking

    monkeypatch.setitem(tracking.ALIGN_PRESETS, "tiny", replace(TRACK_ALIGN, sample_step_px=1, min_points=50))
    return TrackingConfig(preset="tiny")


def test_replay_tracks_by_default_and_is_as_accurate_as_frames_alone(tiny, tmp_path: Path) -> None:
    """The test split's views are 90-120 degrees apart: nothing is trackable, every frame falls back to SCR (counted)
    and the poses are SCR's; --no-tracking gives the same poses without the counts."""
    from acesplat.apps.edge_cli import app

    runs = {}
    for flag in ("--tracking", "--no-tracking"):
        out = tmp_path / f"{flag}.json"
        r = CliRunner().invoke(app, ["replay", str(tiny["bundle"]), str(tiny["scene"]), flag, "--json", str(out)])
        assert r.exit_code == 0, r.output
        runs[flag] = json.loads(out.read_text())
    on, off = runs["--tracking"], runs["--no-tracking"]
    assert on["tracking_enabled"] and not off["tracking_enabled"]
    assert off["scr"] == off["frames"] == 4 and off["tracked"] == off["fallbacks"] == off["reanchors"] == 0
    assert on["tracked"] == 0 and on["scr"] + on["reanchors"] == 4 and on["fallbacks"] == on["reanchors"] >= 1
    assert on["localized"] >= off["localized"] and on["median_translation_m"] <= off["median_translation_m"] + 1e-9


def test_tracked_frames_are_as_accurate_and_a_loss_mid_run_reanchors(tiny, tiny_preset, tmp_path: Path) -> None:
    """A camera that holds each view for three frames: the held frames are tracked (no inference), as accurate as
    SCR on them; a black frame mid-run fails tracking, falls back to SCR, is LOST, and the next frame re-initializes
    from SCR; the covariance travels with every TRACKING pose."""
    from acesplat.core.bundle import load_bundle
    from acesplat.core.pose import TrackingState
    from edge.loop import run_loop
    from edge.replay import replay_split
    from edge.runtime import EdgeLocalizer
    from edge.sources import ReplaySource

    b = load_bundle(tiny["bundle"])
    seq = _sequence(Path(tiny["scene"]), tmp_path / "seq" / "test")
    alone = replay_split(EdgeLocalizer(b, "fp32", 1), seq.parent, "test")
    tracked = replay_split(EdgeLocalizer(b, "fp32", 1, tracking=tiny_preset), seq.parent, "test")
    assert tracked["tracked"] >= 6 and tracked["frames"] == 12, tracked
    assert tracked["localized"] >= alone["localized"]
    assert tracked["median_translation_m"] <= alone["median_translation_m"] + 0.01
    assert tracked["timing_ms"]["inference"]["p50"] == 0.0  # most frames skip the network

    blank = _sequence(Path(tiny["scene"]), tmp_path / "blank" / "test", blank=4)
    loc = EdgeLocalizer(b, "fp32", 1, tracking=tiny_preset)
    outs = []
    run_loop(ReplaySource(blank), loc, outs.append)
    modes = [o.mode for o in outs]
    assert modes[:3] == ["scr", "tracked", "tracked"] and outs[4].fallback is not None
    assert outs[4].record.state == TrackingState.LOST and outs[4].mode == "reanchor"
    assert modes[5] == "scr" and outs[5].record.state == TrackingState.TRACKING  # re-initialized after the loss
    for o in outs:
        if o.record.state == TrackingState.TRACKING:
            assert o.record.covariance is not None and o.record.covariance.shape == (6, 6)
            assert np.all(np.linalg.eigvalsh(o.record.covariance) > 0)


def test_a_blank_query_is_no_match_for_the_flow() -> None:
    """DIS flow from a textured reference to a black frame is zero and consistent both ways, so the forward-backward
    check keeps it; the gray-level check of TRACK_ALIGN does not."""
    from dataclasses import replace

    import cv2

    from acesplat.align.flow_pnp import TRACK_ALIGN, dis_flow, flow_to_query, sample_grid

    rng = np.random.default_rng(0)
    ref = cv2.GaussianBlur(rng.integers(0, 256, (96, 128)).astype(np.uint8), (5, 5), 1.5)
    ys, xs = sample_grid(96, 128, 4)
    at = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    black = np.zeros_like(ref)
    _, keep_fb, _ = flow_to_query(ref, black, at, dis_flow(TRACK_ALIGN), replace(TRACK_ALIGN, max_photo_diff=None))
    _, keep, _ = flow_to_query(ref, black, at, dis_flow(TRACK_ALIGN), TRACK_ALIGN)
    assert keep_fb.mean() > 0.5 and keep.mean() < 0.05
    _, same, _ = flow_to_query(ref, ref.copy(), at, dis_flow(TRACK_ALIGN), TRACK_ALIGN)
    assert same.mean() > 0.9
    with pytest.raises(ValueError, match="max_photo_diff"):
        replace(TRACK_ALIGN, max_photo_diff=0.0)


def test_a_source_that_went_away_ends_tracking(tiny, tiny_preset, tmp_path: Path) -> None:
    """After 'disconnected' the camera may be anywhere: the next frame is solved by SCR from scratch (no prediction,
    no reset counted, no motion check against the pose before the gap)."""
    from acesplat.core.bundle import load_bundle
    from edge.loop import LoopEvent
    from edge.runtime import EdgeLocalizer
    from edge.sources import ReplaySource

    seq = _sequence(Path(tiny["scene"]), tmp_path / "seq" / "test")
    src = ReplaySource(seq)
    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", 1, tracking=tiny_preset)
    modes = [loc.localize(src.read()).mode for _ in range(3)]
    assert modes == ["scr", "tracked", "tracked"] and loc.previous is not None
    loc.notify(LoopEvent("disconnected", "camera 0: read failed", 0.0))
    assert loc.previous is None and loc.tracker.history == [] and loc.tracker.plan() == Plan("scr")
    out = loc.localize(src.read())
    assert out.mode == "scr" and not out.reset and out.fallback is None
