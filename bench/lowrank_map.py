"""Does a head mapped on the low-rank encoder keep more test cells than an exact-encoder map run on it?

`acesplat export --encoder-rank R` fits the encoder's last 3x3 layer to the scene's training images after mapping,
so the head meets features it was not trained on. This maps the scene on the rank-R encoder instead (the default
recipe otherwise) and prints the test cells within 1 / 2 / 4 / 10 px and the per-frame PnP translation error (cm)
of: the exact map on the exact encoder, the exact map on the rank-R encoder, and the rank-R map on it.

    python bench/lowrank_map.py SCENE EXACT_MAP [--rank 128] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cell_accuracy import split_cell_accuracy  # noqa: E402

from acesplat.core.atomic import write_json  # noqa: E402
from acesplat.core.machine import machine_line  # noqa: E402
from acesplat.core.scene import read_split  # noqa: E402
from acesplat.scr.encoders import load_encoder  # noqa: E402
from acesplat.scr.localize import Localizer  # noqa: E402
from acesplat.scr.lowrank import lowrank_encoder  # noqa: E402
from acesplat.scr.mapfile import load_map  # noqa: E402
from acesplat.scr.mapping import MappingConfig, default_short_side, load_training_images, map_scene  # noqa: E402
from acesplat.scr.network import SCRNetwork  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", type=Path)
    ap.add_argument("exact_map", type=Path)
    ap.add_argument("--rank", type=int, default=128)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    print(machine_line())
    enc, _ = load_encoder(None)
    train, test = read_split(args.scene, "train"), read_split(args.scene, "test")
    side = default_short_side(train)
    enc_lr, rep = lowrank_encoder(enc, [im.gray for im in load_training_images(train, side)], args.rank)

    def cells(net: SCRNetwork) -> dict:
        rows = split_cell_accuracy(test, Localizer(net.eval(), side, {}))
        return {
            "within_px": np.mean([r["within_px"] for r in rows], axis=0).round(3).tolist(),
            "pose_cm": [round(r["pose_translation_cm"], 2) for r in rows],
        }

    m = load_map(args.exact_map)
    out = {"rank": args.rank, "kept_variance": rep["kept_variance"], "machine": machine_line()}
    out["exact map, exact encoder"] = cells(SCRNetwork(enc, m.head))
    out["exact map, rank encoder"] = cells(SCRNetwork(enc_lr, m.head))
    t0 = time.monotonic()
    res = map_scene(train, enc_lr, MappingConfig(short_side=side))
    out["rank map seconds"] = time.monotonic() - t0
    out["rank map, rank encoder"] = cells(SCRNetwork(enc_lr, res.head))
    print(json.dumps(out, indent=1))
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
