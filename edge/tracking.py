"""Tracking between frames on the edge (torch-free): the last precise poses seed the next frame.

A constant-velocity prediction from the last two precise poses seeds a cheap flow + PnP
alignment (acesplat.align.flow_pnp.TRACK_ALIGN) of the frame against the nearest bundle keyframe, or, for a bundle
without keyframes, against the last frame SCR solved (its depth from its scene coordinates). SCR + PnP + the gate run
to initialize, every ``reanchor_every`` frames to re-anchor, and whenever the tracked alignment is unsure (it keeps
the predicted pose: too few pairs or inliers, a correction too large) or the prediction moves farther than a frame is
tracked (the history is then kept: frames stay SCR until the motion slows); with keyframes, an SCR pose is refined
by the precise keyframe alignment of --align (KEYFRAME_ALIGN), not the cheap one. A re-anchor farther than
``reset_m``/``reset_deg`` from a moving prediction (two poses known) increments the pose record's
``reset_counter``. When SCR is unsure (the gate) the frame is LOST and tracking starts again from SCR; so it does
after the source went away (``Tracker.lost``: the camera may be anywhere when it is back).

Velocity is per camera frame, counted by the sources' frame ids: a frame the loop dropped (latest frame wins) still
advances the id, so the prediction for a frame three ids after the last pose is three steps of the velocity, and
a velocity measured across a gap is divided by it (acesplat.core.geometry.pose_power). Without ids (None) a step
is a processed frame.

``Tracker`` is the state machine alone (poses in, decisions out); edge.runtime.EdgeLocalizer runs the images.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from acesplat.align.flow_pnp import (
    KEYFRAME_ALIGN,
    TRACK_ALIGN,
    AlignConfig,
    Alignment,
    dis_flow,
    flow_to_query,
    gradient,
    refine_pose,
    sample_grid,
)
from acesplat.align.keyframe_align import Keyframe, _depth_at, anchor_inliers, resample_to
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.geometry import invert_pose, pose_error, pose_power
from acesplat.core.grid import cell_centers
from acesplat.core.pose_refine import reprojection

ALIGN_PRESETS: dict[str, AlignConfig] = {"track": TRACK_ALIGN, "keyframe": KEYFRAME_ALIGN}
"""Alignment presets a tracked frame can use, by name (acesplat.align.flow_pnp)."""
MODES = ("scr", "tracked", "reanchor")
"""How a pose was made: SCR with nothing to track from (start, after LOST, tracking off); the tracked alignment;
SCR while tracking (the re-anchor schedule, or a fallback from an unsure alignment)."""


@dataclass(frozen=True)
class TrackingConfig:
    """When frames are tracked instead of solved from scratch (edge.tracking)."""

    enabled: bool = knob(True, "Track between frames (live and video sources; replay treats a split as a sequence).")
    reanchor_every: int = knob(10, "While tracking, SCR + PnP re-anchors every this many frames (catches drift).")
    max_motion_m: float = knob(0.15, "Predicted motion between frames (m) up to which a frame is tracked; else SCR.")
    max_motion_deg: float = knob(10.0, "Predicted rotation between frames (deg) up to which a frame is tracked.")
    reset_m: float = knob(0.05, "A re-anchor this far (m) from the tracked prediction is a jump: reset_counter += 1.")
    reset_deg: float = knob(2.0, "A re-anchor turned this far (deg) from the tracked prediction is a jump.")
    preset: str = knob("track", "Alignment preset of tracked frames: track (TRACK_ALIGN) or keyframe (KEYFRAME_ALIGN).")
    keyframes: int = knob(1, "Bundle keyframes a tracked frame is aligned against, nearest first.")
    infer_tracked: bool = knob(
        False, "Run SCR on tracked frames too: the alignment must then keep the SCR inliers (slower, stricter)."
    )

    def __post_init__(self) -> None:
        if self.reanchor_every < 1 or self.keyframes < 1:
            raise ValueError(f"reanchor_every and keyframes must be >= 1, got {self.reanchor_every}, {self.keyframes}")
        for name in ("max_motion_m", "max_motion_deg", "reset_m", "reset_deg"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.preset not in ALIGN_PRESETS:
            raise ValueError(f"tracking preset must be one of {', '.join(ALIGN_PRESETS)}, got {self.preset!r}")

    @property
    def align(self) -> AlignConfig:
        return ALIGN_PRESETS[self.preset]


@dataclass(frozen=True)
class Plan:
    """What to do with the next frame: ``mode`` 'track' (align from ``prediction``), 'scr' or 'reanchor' (SCR);
    ``reason`` why a frame that could have been tracked is solved by SCR ('too_far'), else None; ``moving``: the
    prediction carries a velocity (two poses), so an SCR pose far from it is a jump, not the frame's own motion."""

    mode: str
    prediction: np.ndarray | None = None
    reason: str | None = None
    moving: bool = False


@dataclass
class Tracker:
    """The tracking state machine: ``plan()`` before a frame, then ``tracked()``, ``unsure()`` + ``solved()``, or
    ``solved()`` with the frame's result."""

    config: TrackingConfig = field(default_factory=TrackingConfig)
    history: list[np.ndarray] = field(default_factory=list)
    """The last (at most two) precise camera-to-world poses, oldest first; empty when there is nothing to track."""
    history_ids: list[int | None] = field(default_factory=list)
    """The frame ids of ``history``'s poses (None where the source gave none)."""
    since_anchor: int = 0
    """Frames since SCR last solved one."""
    reset_counter: int = 0

    def steps(self, frame_id: int | None) -> tuple[float, float]:
        """(frames from the last pose to ``frame_id``, frames between the last two poses) by the frame ids; (1, 1)
        where ids are missing or do not increase (a source that restarted its count)."""
        ids = self.history_ids
        if frame_id is None or len(ids) < 2 or ids[-1] is None or ids[-2] is None:
            return 1.0, 1.0
        ahead, between = frame_id - ids[-1], ids[-1] - ids[-2]
        if ahead < 1 or between < 1:
            return 1.0, 1.0
        return float(ahead), float(between)

    def predict(self, frame_id: int | None = None) -> np.ndarray | None:
        """The camera-to-world (4, 4) of frame ``frame_id`` at constant velocity per frame (one step when ids are not
        known), or None without a pose."""
        if not self.history:
            return None
        last = self.history[-1]
        if len(self.history) < 2:
            return last.copy()
        d = invert_pose(self.history[-2]) @ last
        ahead, between = self.steps(frame_id)
        return last @ (d if ahead == between else pose_power(d, ahead / between))

    def plan(self, frame_id: int | None = None) -> Plan:
        """Frame ``frame_id``'s plan (does not change the state)."""
        cfg = self.config
        prediction = self.predict(frame_id)
        if not cfg.enabled or prediction is None:
            return Plan("scr")
        moving = len(self.history) == 2
        dt, dr = pose_error(prediction, self.history[-1])
        if dt > cfg.max_motion_m or dr > cfg.max_motion_deg:
            return Plan("scr", None, "too_far")
        if self.since_anchor >= cfg.reanchor_every:
            return Plan("reanchor", prediction, None, moving)
        return Plan("track", prediction, None, moving)

    def plan_after(self, plan: Plan) -> Plan:
        """The mode the frame after one planned ``plan`` gets if that frame goes as planned (tracked, or solved by
        SCR): 'reanchor' when it completes the interval, 'track' otherwise, 'scr' without tracking. The mode only,
        without a prediction (that frame's is made when it is planned). Does not change the state."""
        cfg = self.config
        if not cfg.enabled:
            return Plan("scr")
        since = self.since_anchor + 1 if plan.mode == "track" else 0
        return Plan("reanchor" if since >= cfg.reanchor_every else "track")

    def tracked(self, T_c2w: np.ndarray, frame_id: int | None = None) -> None:
        """The tracked alignment gave frame ``frame_id``'s pose (4, 4)."""
        self._push(T_c2w, frame_id)
        self.since_anchor += 1

    def solved(self, T_c2w: np.ndarray | None, plan: Plan, frame_id: int | None = None) -> bool:
        """SCR solved frame ``frame_id``, planned by ``plan`` (``T_c2w`` (4, 4) or None when the gate refused it:
        LOST). True when the pose jumped from the tracked prediction (``reset_counter`` then incremented)."""
        self.since_anchor = 0
        if T_c2w is None:
            self._forget()
            return False
        jump = False
        if plan.prediction is not None and plan.moving:
            dt, dr = pose_error(T_c2w, plan.prediction)
            jump = dt > self.config.reset_m or dr > self.config.reset_deg
        if jump:
            self._forget()  # the velocity before the jump says nothing about the next frame
            self.reset_counter += 1
        self._push(T_c2w, frame_id)
        return jump

    def lost(self) -> None:
        """The source went away: the motion model no longer holds, the next frame is SCR's (not a re-anchor, so no
        reset is counted)."""
        self._forget()
        self.since_anchor = 0

    def _forget(self) -> None:
        """No pose to track from: the history and its frame ids go together."""
        self.history.clear()
        self.history_ids.clear()

    def _push(self, T: np.ndarray, frame_id: int | None) -> None:
        self.history = [*self.history[-1:], np.asarray(T, np.float64).copy()]
        self.history_ids = [*self.history_ids[-1:], None if frame_id is None else int(frame_id)]


def frame_keyframe(
    gray: np.ndarray, intrinsics: Intrinsics, coords: np.ndarray, stride: int, T_c2w: np.ndarray, threshold_px: float
) -> Keyframe:
    """A frame SCR solved as a keyframe to track from: ``gray`` (H, W) uint8 with ``intrinsics``, its pose
    ``T_c2w`` (4, 4) and the z-depth of its scene coordinates ``coords`` (h, w, 3) (cells ``stride`` px apart) where
    they reproject within ``threshold_px`` (0 elsewhere)."""
    h, w = coords.shape[:2]
    X = np.asarray(coords, np.float64).reshape(-1, 3)
    uv = cell_centers(h, w, stride)
    finite = np.all(np.isfinite(X), axis=1)
    w2c = invert_pose(T_c2w)
    Xc, _, err = reprojection(np.where(finite[:, None], X, 0.0), uv, intrinsics.K, w2c[:3, :3], w2c[:3, 3])
    depth = np.where(finite & (err < threshold_px), Xc[:, 2], 0.0).reshape(h, w).astype(np.float32)
    return Keyframe(gray, intrinsics, np.asarray(T_c2w, np.float64), depth, stride)


_REFERENCE_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
CACHED_REFERENCES = 16
"""Keyframes whose sampled points are kept between frames (tracking returns to the same few)."""
CANDIDATES_PER_PAIR = 1.5
"""Textured reference pixels flowed per pair PnP may get (cfg.max_pairs): thinned before the flow, not after."""


def _reference_points(kf: Keyframe, cfg: AlignConfig) -> tuple[np.ndarray, np.ndarray]:
    """A keyframe's textured pixels with depth (M, 2) on ``cfg``'s sample grid, evenly thinned to
    CANDIDATES_PER_PAIR x ``cfg.max_pairs``, and their world points (M, 3); cached per keyframe."""
    key = (
        kf.c2w.tobytes(),
        hash(kf.gray.tobytes()),
        kf.gray.shape,
        kf.intrinsics,
        cfg.sample_step_px,
        cfg.min_gradient,
        cfg.max_pairs,
    )
    hit = _REFERENCE_CACHE.get(key)
    if hit is not None:
        return hit
    h, w = kf.gray.shape
    ys, xs = sample_grid(h, w, cfg.sample_step_px)
    u, v = xs.ravel().astype(np.float64), ys.ravel().astype(np.float64)
    textured = gradient(kf.gray)[ys.ravel(), xs.ravel()] > cfg.min_gradient
    z = _depth_at(kf, u, v)
    use = np.flatnonzero(textured & (z > 0) & np.isfinite(z))
    cap = int(CANDIDATES_PER_PAIR * cfg.max_pairs)
    if cfg.max_pairs and len(use) > cap:
        use = use[np.unique(np.linspace(0, len(use) - 1, cap).round().astype(np.int64))]
    at = np.stack([u[use], v[use]], axis=1)
    X = kf.intrinsics.unproject(at, z[use]) @ kf.c2w[:3, :3].T + kf.c2w[:3, 3]
    if len(_REFERENCE_CACHE) >= CACHED_REFERENCES:
        _REFERENCE_CACHE.pop(next(iter(_REFERENCE_CACHE)))
    _REFERENCE_CACHE[key] = (at, X)
    return at, X


def track_to_keyframes(
    gray: np.ndarray,
    intrinsics: Intrinsics,
    start_c2w: np.ndarray,
    keyframes: Sequence[Keyframe],
    cfg: AlignConfig = TRACK_ALIGN,
    anchor: tuple[np.ndarray, np.ndarray] | None = None,
) -> Alignment:
    """The query ``gray`` (H, W) uint8 with ``intrinsics`` aligned to ``keyframes`` from ``start_c2w`` (4, 4): the
    keyframes' textured pixels with depth carried by flow straight to the query (no warp to the start pose: between
    frames the views differ by centimetres, which DIS's pyramid spans), one PnP under ``cfg``'s guards, so the start
    pose seeds PnP and bounds the correction. ``anchor`` (points (N, 3), pixels (N, 2)): the SCR correspondences the
    aligned pose must keep (``cfg.min_anchor_kept``), as acesplat.align.keyframe_align.align_to_keyframes."""
    if gray.ndim != 2 or gray.dtype != np.uint8 or gray.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"query must be (H, W) uint8 matching its intrinsics, got {gray.shape} {gray.dtype}")
    start = np.asarray(start_c2w, np.float64)
    if not keyframes:
        return Alignment(start, "few_points")
    flow = dis_flow(cfg)
    Xs, uvs, errs = [], [], []
    for kf in keyframes:
        query = resample_to(gray, intrinsics, kf.intrinsics)
        at, X = _reference_points(kf, cfg)
        seen, keep, err = flow_to_query(kf.gray, query, at, flow, cfg, cfg.first_flow_scale)
        H = intrinsics.K @ np.linalg.inv(kf.intrinsics.K)  # back to the query's own pixels
        uvh = np.c_[seen[keep], np.ones(int(keep.sum()))] @ H.T
        Xs.append(X[keep])
        uvs.append(uvh[:, :2] / uvh[:, 2:3])
        errs.append(err[keep])
    X, uv, err = np.concatenate(Xs), np.concatenate(uvs), np.concatenate(errs)
    al = refine_pose(start, intrinsics, lambda _pose, _r: (X, uv, err), cfg, rounds=1)
    if al.status != "aligned" or anchor is None:
        return al
    if anchor_inliers(anchor, intrinsics, al.pose) < cfg.min_anchor_kept * anchor_inliers(anchor, intrinsics, start):
        return Alignment(start, "disagrees", al.points, al.inliers, al.shift_m, al.shift_deg)
    return al
