"""Which localized frames become keyframes for refinement.

A keyframe must be trustworthy (the PnP solution passed the gate with enough inliers, so a wrong
pose is unlikely) and must add something: the camera moved or turned enough since the last keyframe,
or the map covers too little of what it sees. Redundant frames would spend the refinement budget on
views the map already fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acesplat.core.config import knob
from acesplat.core.geometry import pose_error


@dataclass(frozen=True)
class KeyframePolicy:
    """Which localized frames become keyframes."""

    min_inliers: int = knob(50, "The PnP gate's count (small inputs have few cells: 80 at 64x80)...")
    min_inlier_ratio: float = knob(0.2, "...plus this share of all cells agreeing (real SCR maps give 20-60%).")
    min_translation_m: float = knob(0.10, "Motion since the last keyframe that makes a new one (m)...")
    min_rotation_deg: float = knob(8.0, "...or this rotation (deg).")
    min_coverage: float = knob(0.85, "A view whose cells the map covers less than this share of is a keyframe.")

    def __post_init__(self) -> None:
        if self.min_inliers < 0 or self.min_translation_m < 0 or self.min_rotation_deg < 0:
            raise ValueError(f"keyframe thresholds must be non-negative, got {self}")
        if not 0.0 <= self.min_inlier_ratio <= 1.0:
            raise ValueError(f"min_inlier_ratio must be in [0, 1], got {self.min_inlier_ratio}")
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ValueError(f"min_coverage must be in [0, 1], got {self.min_coverage}")


def keyframe_decision(
    pose_c2w: np.ndarray | None,
    inliers: int,
    tracking: bool,
    last_keyframe_pose: np.ndarray | None,
    coverage: float | None,
    policy: KeyframePolicy = KeyframePolicy(),
    inlier_ratio: float = 1.0,
) -> tuple[bool, str]:
    """(is a keyframe, reason). Reasons: 'lost', 'inliers', 'first', 'viewpoint', 'coverage', 'redundant'.

    pose_c2w (4, 4) the frame's estimated pose; coverage the share of the view the map covers (None:
    unknown, then only motion counts); inlier_ratio inliers / correspondences.
    """
    if not tracking or pose_c2w is None or not np.all(np.isfinite(pose_c2w)):
        return False, "lost"
    if inliers < policy.min_inliers or inlier_ratio < policy.min_inlier_ratio:
        return False, "inliers"
    if last_keyframe_pose is None:
        return True, "first"
    t_m, r_deg = pose_error(np.asarray(pose_c2w, np.float64), np.asarray(last_keyframe_pose, np.float64))
    if t_m >= policy.min_translation_m or r_deg >= policy.min_rotation_deg:
        return True, "viewpoint"
    if coverage is not None and coverage < policy.min_coverage:
        return True, "coverage"
    return False, "redundant"


class KeyframeSelector:
    """Remembers the last accepted keyframe pose and counts decisions by reason."""

    def __init__(self, policy: KeyframePolicy = KeyframePolicy()) -> None:
        self.policy = policy
        self.last_pose: np.ndarray | None = None
        self.counts: dict[str, int] = {}

    def consider(
        self,
        pose_c2w: np.ndarray | None,
        inliers: int,
        tracking: bool,
        coverage: float | None = None,
        inlier_ratio: float = 1.0,
    ) -> bool:
        ok, reason = keyframe_decision(pose_c2w, inliers, tracking, self.last_pose, coverage, self.policy, inlier_ratio)
        self.counts[reason] = self.counts.get(reason, 0) + 1
        return ok

    def accept(self, pose_c2w: np.ndarray) -> None:
        """Call when a keyframe was committed to the map (a rolled-back one does not move the reference)."""
        self.last_pose = np.array(pose_c2w, np.float64, copy=True)
