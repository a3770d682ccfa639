"""Time a default map's head steps in windows of 250: does a long run slow down as it goes?

    python bench/map_step_curve.py SCENE OUT.json

Maps SCENE with the default recipe (the map itself is not kept) and prints ms per head step in each window, the
map's seconds and its buffer's, with the machine.
"""

from __future__ import annotations

import argparse
import time

from acesplat.core.atomic import write_json
from acesplat.core.machine import machine_line
from acesplat.core.scene import read_split
from acesplat.scr.encoders import load_encoder
from acesplat.scr.mapping import MappingConfig, default_short_side, map_scene

WINDOW = 250


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    args = ap.parse_args()
    split = read_split(args.scene, "train")
    enc, _ = load_encoder(None)
    cfg = MappingConfig(short_side=default_short_side(split))
    marks: list[tuple[int, float]] = []
    t0 = time.perf_counter()

    def progress(phase: str, p: float, info: dict) -> None:
        if phase == "train" and (info["iteration"] % WINDOW == 0 or info["iteration"] == 1):
            marks.append((info["iteration"], time.perf_counter() - t0))

    res = map_scene(split, enc, cfg, progress)
    curve = [(b[0], (b[1] - a[1]) / (b[0] - a[0]) * 1000) for a, b in zip(marks, marks[1:])]
    print(machine_line())
    print(f"map {res.seconds:.1f} s, buffer {res.buffer_seconds:.1f} s")
    for it, ms in curve:
        print(f"steps to {it:5d}: {ms:6.1f} ms/step")
    write_json(
        args.out, {"machine": machine_line(), "seconds": res.seconds, "buffer": res.buffer_seconds, "curve": curve}
    )


if __name__ == "__main__":
    main()
