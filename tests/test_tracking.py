"""Tracking between frames: the state machine on synthetic poses, then the edge runtime on the tiny bundle."""

from __future__ import annotations

import numpy as np
import pytest

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
