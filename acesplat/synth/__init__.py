"""The built-in synthetic scene: a procedurally furnished, photo-textured room rendered by numpy ray casting.

Torch-free. ``make_room`` builds a room from a seed, ``make_trajectory`` a camera pass through it,
``render_view`` renders RGB and metric z-depth, ``synthesize`` writes the built-in scene in the ACE
layout, ``random_scene_frames`` yields varied in-memory scenes for encoder pretraining.
"""

from acesplat.synth.dataset import (
    SynthConfig,
    SynthFrame,
    default_intrinsics,
    random_scene,
    random_scene_frames,
    render_frames,
    synthesize,
)
from acesplat.synth.render import render_view
from acesplat.synth.room import RoomScene, make_room
from acesplat.synth.trajectory import TEST_PASS, TRAIN_PASS, CameraPath, make_trajectory

__all__ = [
    "TEST_PASS",
    "TRAIN_PASS",
    "CameraPath",
    "RoomScene",
    "SynthConfig",
    "SynthFrame",
    "default_intrinsics",
    "make_room",
    "make_trajectory",
    "random_scene",
    "random_scene_frames",
    "render_frames",
    "render_view",
    "synthesize",
]
