"""The pose record the edge runtime produces and the firmware bridge sends."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np


class TrackingState(enum.IntEnum):
    """Whether the last frame was localized (passed the inlier gate)."""

    LOST = 0
    TRACKING = 1


@dataclass
class PoseRecord:
    """One localization result.

    ``T_c2w`` (4, 4) is camera-to-world with OpenCV camera axes, in metres; ``timestamp_us`` is the
    capture time in microseconds; ``quality`` is in [0, 1] (inlier ratio of the PnP solution).
    ``covariance`` (6, 6), when known, is the pose's uncertainty in the world frame: position (m^2) then a rotation
    vector applied on the left (rad^2). ``reset_counter`` increments whenever the pose source jumps (a re-anchor
    that moved the pose), so a consumer's filter can reset instead of fusing the jump.
    """

    timestamp_us: int
    T_c2w: np.ndarray = field(default_factory=lambda: np.eye(4))
    inliers: int = 0
    state: TrackingState = TrackingState.LOST
    quality: float = 0.0
    frame_id: int = 0
    covariance: np.ndarray | None = None
    reset_counter: int = 0
