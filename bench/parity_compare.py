"""Compare two trees' numbers from bench/parity.sh: python bench/parity_compare.py OUT TAG_A TAG_B.

Every field is compared exactly (per-frame lists, lifecycle counts, histories included) except timings, paths and
fields that name the machine or the software run; the printed row shows the headline numbers.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HEADLINE = (
    "frames",
    "localized",
    "median_translation_m",
    "median_rotation_deg",
    "recall_5cm_5deg",
    "psnr",
    "train_psnr",
    "gaussians_final",
)
TIMING = ("ms", "seconds", "_s", "fps", "timing", "time", "elapsed")
SKIP = {"bundle", "scene", "map", "source", "path", "cpu_isa", "onnxruntime", "provider", "torch_threads", "renders"}


def strip(v, key: str = ""):
    """``v`` without timing fields, recursively."""
    if isinstance(v, dict):
        return {k: strip(x, k) for k, x in v.items() if k not in SKIP and not any(t in k for t in TIMING)}
    if isinstance(v, list):
        return [strip(x, key) for x in v]
    return v


def first_difference(a, b, where: str = "") -> str | None:
    if type(a) is not type(b):
        return f"{where}: {a!r} vs {b!r}"
    if isinstance(a, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                return f"{where}.{k}: only in one"
            d = first_difference(a[k], b[k], f"{where}.{k}")
            if d:
                return d
        return None
    if isinstance(a, list):
        if len(a) != len(b):
            return f"{where}: {len(a)} vs {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b)):
            d = first_difference(x, y, f"{where}[{i}]")
            if d:
                return d
        return None
    return None if a == b else f"{where}: {a!r} vs {b!r}"


def main(out: Path, a: str, b: str) -> int:
    differ = 0
    for scene in ("room", "herz"):
        for fa in sorted((out / a / scene).glob("*.json")):
            fb = out / b / scene / fa.name
            if not fb.is_file():
                print(f"{scene:5s} {fa.stem:18s} missing in {b}")
                differ += 1
                continue
            ja, jb = json.loads(fa.read_text()), json.loads(fb.read_text())
            d = first_difference(strip(ja), strip(jb))
            differ += d is not None
            cells = "  ".join(
                f"{k}={ja[k]:.6g}" if isinstance(ja[k], float) else f"{k}={ja[k]}" for k in HEADLINE if k in ja
            )
            print(f"{scene:5s} {fa.stem:18s} {'same' if d is None else 'DIFFERENT: ' + d}  {cells}")
        ma, mb = out / a / scene / "bundle" / "manifest.json", out / b / scene / "bundle" / "manifest.json"
        if ma.is_file() and mb.is_file():  # the export's self-checks (ONNX bytes differ only by embedded paths)
            d = first_difference(
                strip(json.loads(ma.read_text())["checks"]), strip(json.loads(mb.read_text())["checks"])
            )
            differ += d is not None
            print(f"{scene:5s} {'export checks':18s} {'same' if d is None else 'DIFFERENT: ' + d}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), sys.argv[2], sys.argv[3]))
