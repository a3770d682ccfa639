"""Firmware bridge: encode-and-write time per pose (target <= 50 us) and the 115200-baud link budget.

    python bench/bench_bridge.py [--n 20000] [--json out.json]

Times each call separately (time.perf_counter_ns) and reports median / p99 / max in microseconds,
so a scheduler hiccup shows up in the tail instead of inflating the typical figure. Other work on
a shared machine makes the tail noisy: the load average is printed beside the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import select
import threading
import time
from pathlib import Path
from statistics import median

import numpy as np
import serial

from acesplat.core.geometry import look_at, matrix_to_quat
from acesplat.core.machine import cpu_model
from acesplat.core.pose import PoseRecord, TrackingState
from firmware_bridge.mavlink import MavlinkConfig, MavlinkEncoder
from firmware_bridge.protocol import MsgType, Pose, RuntimeState, Status, encode_frame, wire_size
from firmware_bridge.sink import FrameEncoder, PoseSink
from firmware_bridge.transport import serial_opener

TARGET_US = 50.0
BAUD = 115200
BYTES_PER_S = BAUD / 10  # 8N1: start + 8 data + stop bits per byte


def machine() -> dict:
    model = cpu_model()
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "load_avg_1_5_15": os.getloadavg(),
    }


def records(n: int) -> list[PoseRecord]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        eye = rng.uniform(-5, 5, 3)
        T = look_at(eye, eye + rng.normal(size=3))
        out.append(
            PoseRecord(
                time.monotonic_ns() // 1000 + i,
                T,
                int(rng.integers(20, 900)),
                TrackingState.TRACKING,
                float(rng.random()),
                i,
            )
        )
    return out


def summarize(ns: list[int], cpu_ns: list[int]) -> dict:
    us = np.asarray(ns) / 1000.0
    return {
        "median_us": round(float(median(us)), 2),
        "p99_us": round(float(np.percentile(us, 99)), 2),
        "max_us": round(float(us.max()), 1),
        "cpu_median_us": round(float(median(cpu_ns)) / 1000.0, 2),
    }


def time_calls(fn, items) -> dict:
    """Wall time per call, plus this thread's CPU time per call: on a shared machine the wall time
    includes waiting for a core, the CPU time is what the call costs once it runs."""
    ns, cpu = [], []
    clock, cpu_clock = time.perf_counter_ns, time.thread_time_ns
    for item in items:
        t0, c0 = clock(), cpu_clock()
        fn(item)
        c1, t1 = cpu_clock(), clock()
        ns.append(t1 - t0)
        cpu.append(c1 - c0)
    return summarize(ns, cpu)


class PtyDrain:
    """A pseudo-terminal whose far end is read as fast as data arrives, like a UART that keeps up."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.name = os.ttyname(self.slave)
        self.bytes = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if select.select([self.master], [], [], 0.05)[0]:
                self.bytes += len(os.read(self.master, 1 << 16))

    def close(self) -> None:
        self._stop.set()
        self._t.join()
        os.close(self.master)
        os.close(self.slave)


def bench_encode_write(recs: list[PoseRecord]) -> dict:
    res: dict = {}
    enc = FrameEncoder()
    res["encode_frame_only"] = time_calls(enc.pose, recs)
    res["  of which core matrix_to_quat"] = time_calls(lambda r: matrix_to_quat(r.T_c2w[:3, :3]), recs)
    drain = PtyDrain()
    pty = serial.serial_for_url(drain.name, baudrate=BAUD, timeout=0, write_timeout=1.0)
    res["encode_write_pty"] = time_calls(lambda r: pty.write(enc.pose(r)), recs)
    mav = MavlinkEncoder(MavlinkConfig())
    res["mavlink_vpe_encode_write_pty"] = time_calls(lambda r: pty.write(mav.pose(r)), recs)
    pty.close()
    drain.close()
    return res


def bench_submit(recs: list[PoseRecord]) -> dict:
    """What the localization loop pays per pose: PoseSink.submit with the writer thread running."""
    drain = PtyDrain()
    sink = PoseSink(serial_opener(drain.name, BAUD))
    out = time_calls(sink.submit, recs)
    sink.close()
    s = sink.stats()
    drain.close()
    out.update(submitted=s.submitted, sent=s.sent, dropped=s.dropped)
    return out


def link_budget() -> dict:
    rec = records(1)[0]
    pose = len(encode_frame(Pose.from_record(rec), 1))
    status = len(encode_frame(Status(0, 30.0, 20.0, 0, 0, RuntimeState.TRACKING), 1))
    assert (pose, status) == (wire_size(MsgType.POSE), wire_size(MsgType.STATUS))
    pose_100hz = 100 * pose / BYTES_PER_S
    status_1hz = status / BYTES_PER_S
    mav = {
        "vpe_unknown_cov": len(MavlinkEncoder(MavlinkConfig()).pose(rec)),
        "vpe_with_cov": len(MavlinkEncoder(MavlinkConfig(pos_std_m=0.05, ang_std_rad=0.03)).pose(rec)),
        "odometry": len(MavlinkEncoder(MavlinkConfig(message="odometry")).pose(rec)),
        "heartbeat": len(MavlinkEncoder().heartbeat()),
    }
    return {
        "baud": BAUD,
        "bytes_per_s_8N1": BYTES_PER_S,
        "pose_frame_bytes": pose,
        "status_frame_bytes": status,
        "pose_100hz_utilisation": round(pose_100hz, 4),
        "status_1hz_utilisation": round(status_1hz, 5),
        "headroom_after_100hz_pose_and_status": round(1 - pose_100hz - status_1hz, 4),
        "max_pose_hz_with_status": round((BYTES_PER_S - status) / pose, 1),
        "mavlink_bytes": mav,
        "mavlink_max_hz_with_heartbeat": {
            k: round((BYTES_PER_S - mav["heartbeat"]) / v, 1) for k, v in mav.items() if k != "heartbeat"
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000, help="poses per measurement")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    recs = records(args.n)
    report = {"machine": machine(), "n": args.n, "target_us": TARGET_US}
    report["per_pose"] = bench_encode_write(recs)
    report["submit"] = bench_submit(recs)
    report["link_budget"] = link_budget()
    report["machine"]["load_avg_after"] = os.getloadavg()

    m = report["machine"]
    print(
        f"machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}, load avg before {m['load_avg_1_5_15']} after "
        f"{m['load_avg_after']}"
    )
    print(
        f"per pose, {args.n} poses, microseconds (wall median / p99 / max, thread CPU median; target {TARGET_US:g} us):"
    )
    for name, r in {**report["per_pose"], "submit (caller side)": report["submit"]}.items():
        print(
            f"  {name:<32} {r['median_us']:8.2f} {r['p99_us']:8.2f} {r['max_us']:8.1f} {r['cpu_median_us']:8.2f}"
            f"   wall median/target = {r['median_us'] / TARGET_US:.2f}, cpu median/target = "
            f"{r['cpu_median_us'] / TARGET_US:.2f}"
        )
    s = report["submit"]
    print(
        f"  submit burst: {s['submitted']} submitted, {s['sent']} sent, {s['dropped']} replaced by a newer pose "
        "(link-limited)"
    )
    b = report["link_budget"]
    print(f"link budget at {BAUD} baud 8N1 ({BYTES_PER_S:g} bytes/s):")
    print(
        f"  POSE frame {b['pose_frame_bytes']} B -> 100 Hz uses {b['pose_100hz_utilisation']:.1%}; "
        f"STATUS {b['status_frame_bytes']} B at 1 Hz uses {b['status_1hz_utilisation']:.2%}; "
        f"headroom {b['headroom_after_100hz_pose_and_status']:.1%}; max POSE rate with STATUS "
        f"{b['max_pose_hz_with_status']} Hz"
    )
    print(f"  MAVLink bytes {b['mavlink_bytes']} -> max Hz with 1 Hz HEARTBEAT {b['mavlink_max_hz_with_heartbeat']}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
