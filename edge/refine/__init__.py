"""Incremental 3DGS refinement on the edge, inside a per-frame latency budget (torch-free).

One concept per module: ``keyframes`` (which frames), ``coverage`` (where the map falls short), ``seeding`` (new
Gaussians from SCR coordinates), ``adam`` (row-masked Adam), ``deadline`` (never start work that would overrun),
``guard`` (non-finite gradients, photometric rollback), ``prune`` (transparency and the cap), ``store`` (the map's
arrays with spare capacity), ``persist`` (atomic periodic PLY), ``refiner`` (one keyframe's batch, as a generator of
timed work pieces), ``worker`` (the refinement thread, carrying a batch over frames' time windows), ``session`` (a
tap of the edge localizer), ``bundle_models`` and ``onnx_seeder`` (what a bundle carries for refinement). The
keyframe's pose is corrected against the map by acesplat.align.flow_pnp.
"""

from edge.refine.deadline import CostEstimate, Deadline
from edge.refine.keyframes import KeyframePolicy, KeyframeSelector, keyframe_decision
from edge.refine.refiner import BatchReport, Keyframe, RefineConfig, Refiner
from edge.refine.session import RefineOptions, RefineSession, start_refinement

__all__ = [
    "BatchReport",
    "CostEstimate",
    "Deadline",
    "Keyframe",
    "KeyframePolicy",
    "KeyframeSelector",
    "RefineConfig",
    "RefineOptions",
    "RefineSession",
    "Refiner",
    "keyframe_decision",
    "start_refinement",
]
