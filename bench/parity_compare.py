"""Compare two trees' numbers from bench/parity.sh: python bench/parity_compare.py OUT TAG_A TAG_B."""

from __future__ import annotations

import json
import sys
from pathlib import Path

KEYS = (
    "frames",
    "localized",
    "median_translation_m",
    "median_rotation_deg",
    "recall_5cm_5deg",
    "recall_10cm_5deg",
    "psnr",
    "ssim",
    "train_psnr",
    "train_ssim",
    "gaussians_initial",
    "gaussians_final",
)


def main(out: Path, a: str, b: str) -> int:
    differ = 0
    for scene in ("room", "herz"):
        for fa in sorted((out / a / scene).glob("*.json")):
            ja, jb = json.loads(fa.read_text()), json.loads((out / b / scene / fa.name).read_text())
            row = {k: (ja.get(k), jb.get(k)) for k in KEYS if k in ja or k in jb}
            same = all(x == y for x, y in row.values())
            differ += not same
            cells = "  ".join(f"{k}={x:.6g}" if isinstance(x, float) else f"{k}={x}" for k, (x, _) in row.items())
            diffs = "  ".join(f"{k}: {x} -> {y}" for k, (x, y) in row.items() if x != y)
            print(
                f"{scene:5s} {fa.stem:18s} {'same' if same else 'DIFFERENT'}  {cells}"
                + (f"\n      {diffs}" if diffs else "")
            )
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), sys.argv[2], sys.argv[3]))
