"""Cost of the Foxglove tap per frame at the bundle's size: on_frame (the localizer's thread) and publish (the tap's
thread: JPEG, every channel, MCAP and a live server). Results: bench/foxglove.md.

    PYTHONPATH=. python bench/bench_foxglove.py [--frames 200] [--size 360x480]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import look_at
from acesplat.core.pose import PoseRecord, TrackingState
from edge.foxglove_tap import FoxgloveTap
from edge.runtime import FrameOutcome
from tests.test_edge_scene import ROOM, _texture, render


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--size", default="360x480")
    a = ap.parse_args()
    h, w = (int(v) for v in a.size.split("x"))
    rng = np.random.default_rng(0)
    tex = [_texture(rng) for _ in range(6)]
    intr = Intrinsics.from_focal(0.9 * w, w, h)
    grays = []
    for i in range(8):  # textured-room views, as the network input (gray)
        yaw = 2 * np.pi * i / 8
        T = look_at(ROOM / 2, ROOM / 2 + np.array([np.cos(yaw), np.sin(yaw), 0.0]))
        rgb, _ = render(tex, T, intr)
        grays.append((rgb.mean(axis=2)).astype(np.uint8))
    with tempfile.TemporaryDirectory() as d:
        tap = FoxgloveTap(port=0, mcap=Path(d) / "b.mcap")
        on_ms, pub_ms = [], []
        for i in range(a.frames):
            T = np.eye(4)
            T[:3, 3] = [0.01 * i, 0, 0]
            rec = PoseRecord(i * 33_000, T, 200, TrackingState.TRACKING, 0.6, i)
            times = dict.fromkeys(("capture", "preprocess", "inference", "pnp", "align", "total"), 1.0)
            out = FrameOutcome(rec, None, times, f"{i}", None, intr, gray=grays[i % len(grays)])
            t0 = time.perf_counter()
            tap.on_frame(out)
            on_ms.append((time.perf_counter() - t0) * 1e3)
            t0 = time.perf_counter()
            tap.publish(out)  # the tap's thread's work, timed here on the caller
            pub_ms.append((time.perf_counter() - t0) * 1e3)
            time.sleep(0.01)
        rep = tap.close()
    print(
        f"{w}x{h} gray, {a.frames} frames: on_frame median {np.median(on_ms):.3f} ms p99 {np.percentile(on_ms, 99):.3f}"
    )
    print(
        f"publish (JPEG + all channels, MCAP + server) median {np.median(pub_ms):.2f} ms "
        f"p99 {np.percentile(pub_ms, 99):.2f} ms; tap thread {rep}"
    )


if __name__ == "__main__":
    main()
