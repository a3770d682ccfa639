"""Firmware bridge fuzz: a million random and mutated frames through the Python and the C decoder.

    python bench/bench_bridge_fuzz.py [--frames 1000000] [--seed 1] [--json out.json]

Pass criteria (exit code 1 otherwise): no exception in Python, no crash or sanitizer report in C
(the C decoder runs under AddressSanitizer and UBSan), no corrupted frame accepted, no intact
frame lost, and both decoders agreeing on every accepted frame and on the reject counts per reason.
The oracle is independent of both decoders: an accepted frame must be byte-identical to a frame
the generator emitted, and every such frame that survived with both delimiters must be accepted.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import zlib
from pathlib import Path

from firmware_bridge.decoder import StreamDecoder
from firmware_bridge.protocol import encode_frame
from firmware_bridge.testing import build_harness, canonical, expected_segments, fuzz_stream, run_harness, stats_line

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_bridge import machine  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    report: dict = {"machine": machine(), "frames": args.frames, "seed": args.seed}

    t = time.perf_counter()
    stream, originals = fuzz_stream(args.frames, args.seed)
    report["generate_s"] = round(time.perf_counter() - t, 2)
    report["stream_bytes"] = len(stream)

    t = time.perf_counter()
    dec = StreamDecoder()
    accepted = []
    for i in range(0, len(stream), 4096):
        accepted += dec.feed(stream[i : i + 4096])
    accepted += dec.feed(b"\x00")
    report["python_decode_s"] = round(time.perf_counter() - t, 2)
    report["python_us_per_frame"] = round(report["python_decode_s"] / args.frames * 1e6, 2)

    expected = expected_segments(stream, originals)
    got = [encode_frame(f.message, f.seq)[:-1] for f in accepted]
    false_accepts = sum(seg not in originals for seg in got)
    report.update(
        accepted=len(got),
        expected=len(expected),
        rejected=dec.frames_rejected,
        rejects=dict(dec.rejects),
        false_accepts=false_accepts,
        python_matches_oracle=got == expected,
    )

    digest = 0
    for f in accepted:
        digest = zlib.crc32((canonical(f) + "\n").encode(), digest)
    py_lines = [f"DIGEST {digest:08x}", stats_line(dec)]

    with tempfile.TemporaryDirectory() as tmp:
        for sanitize in (True, False):
            exe = build_harness(Path(tmp), sanitize=sanitize)
            t = time.perf_counter()
            c_lines = run_harness(exe, "digest", stream + b"\x00").splitlines()
            key = "c_asan_ubsan" if sanitize else "c_O2"
            report[f"{key}_decode_s"] = round(time.perf_counter() - t, 2)
            report[f"{key}_matches_python"] = c_lines == py_lines
    report["machine"]["load_avg_after"] = os.getloadavg()

    ok = (
        report["python_matches_oracle"]
        and false_accepts == 0
        and report["c_asan_ubsan_matches_python"]
        and report["c_O2_matches_python"]
    )
    report["pass"] = ok
    m = report["machine"]
    print(
        f"machine: {m['cpu']}, {m['cores']} cores, load avg before {m['load_avg_1_5_15']} after {m['load_avg_after']}"
    )
    print(
        f"{args.frames} frames (seed {args.seed}), {len(stream) / 1e6:.1f} MB stream, generated in "
        f"{report['generate_s']} s"
    )
    print(
        f"python: {report['python_decode_s']} s ({report['python_us_per_frame']} us/frame); accepted {len(got)} = "
        f"intact frames {len(expected)}: "
        f"{report['python_matches_oracle']}; corrupted accepted: {false_accepts}; rejected {dec.frames_rejected} "
        f"{dict(dec.rejects)}"
    )
    print(
        f"C (ASan+UBSan): {report['c_asan_ubsan_decode_s']} s, identical to Python: "
        f"{report['c_asan_ubsan_matches_python']}; "
        f"C (-O2): {report['c_O2_decode_s']} s, identical: {report['c_O2_matches_python']}"
    )
    print("PASS" if ok else "FAIL")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
