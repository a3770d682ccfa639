"""Writes synth_reference.npz, the pixels tests/test_synth.py compares the built-in scene against.

Run it only on purpose (a change to the synthetic scene), with the OpenCV release pyproject.toml allows:
    python tests/data/make_synth_reference.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from acesplat.synth import synthesize  # noqa: E402

SEED, TRAIN, TEST, SIZE = 0, 2, 1, (48, 64)
FRAMES = ("train/rgb/frame-00000.png", "train/rgb/frame-00001.png", "test/rgb/frame-00000.png")


def render() -> dict[str, np.ndarray]:
    with tempfile.TemporaryDirectory() as d:
        synthesize(Path(d) / "s", seed=SEED, train_frames=TRAIN, test_frames=TEST, size=SIZE)
        return {f: cv2.imread(str(Path(d) / "s" / f), cv2.IMREAD_COLOR) for f in FRAMES}


if __name__ == "__main__":
    imgs = render()
    np.savez_compressed(
        Path(__file__).with_name("synth_reference.npz"),
        opencv=cv2.__version__,
        **{f.replace("/", "__"): v for f, v in imgs.items()},
    )
