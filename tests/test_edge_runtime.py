"""The edge runtime end to end on the tiny exported bundle: replay accuracy, the commands, faults and Ctrl-C."""

from __future__ import annotations

import json
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.apps.edge_cli import app
from acesplat.core.bundle import INT8_PRECISIONS, load_bundle
from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import pose_error
from acesplat.core.metrics import RECALL_THRESHOLDS
from acesplat.core.pose import TrackingState
from acesplat.core.scene import read_split
from edge.loop import run_loop
from edge.replay import replay_split, timing_summary
from edge.runtime import STAGES, EdgeLocalizer, FrameOutcome, PnPSettings
from edge.sources import CameraSource, ReplaySource, SourceFrame

STAT_KEYS = {"mean", "p50", "p90", "p95", "p99", "max"}


@pytest.fixture(scope="module")
def localizer(tiny) -> EdgeLocalizer:
    return EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", threads=1)


def test_replay_localizes_like_the_desktop_path(tiny, localizer) -> None:
    from acesplat.scr.localize import Localizer, evaluate
    from acesplat.scr.mapfile import encoder_for_map, load_map

    s = replay_split(localizer, tiny["scene"], "test")
    assert s["frames"] == 4 and s["localized"] == 4
    assert s["median_translation_m"] < 0.25 and s["median_rotation_deg"] < 6.0  # measured 18.6 cm, 4.4 deg
    m = load_map(tiny["map"])
    ref = evaluate(read_split(tiny["scene"], "test"), Localizer(m.network(encoder_for_map(m, tiny["map"])), 64, {}))
    assert ref["localized"] == s["localized"]
    assert abs(ref["median_translation_m"] - s["median_translation_m"]) < 0.01
    assert abs(ref["median_rotation_deg"] - s["median_rotation_deg"]) < 0.2


def test_replay_command_json_has_eval_keys_and_stage_timings(tiny, tmp_path: Path) -> None:
    out = tmp_path / "r.json"
    r = CliRunner().invoke(
        app, ["replay", str(tiny["bundle"]), str(tiny["scene"]), "--int8", "--threads", "1", "--json", str(out)]
    )
    assert r.exit_code == 0, r.output
    s = json.loads(out.read_text())
    for k in (
        "frames",
        "localized",
        "median_translation_m",
        "median_rotation_deg",
        "mean_ms",
        "per_frame",
        *RECALL_THRESHOLDS,
    ):
        assert k in s
    assert set(s["timing_ms"]) == set(STAGES)
    assert all(set(v) == STAT_KEYS for v in s["timing_ms"].values())
    assert (
        s["precision"] in ("int8", "int8_vnni") and s["localized"] >= 3
    )  # INT8 keeps most frames localized (measured 4)
    assert s["median_translation_m"] < 0.3  # measured 21.7 cm
    gt = {f.name: f.pose for f in read_split(tiny["scene"], "test").frames}
    for f in s["per_frame"]:  # each frame's pose, whose error against the true pose is the one reported
        if f["translation_m"] is not None:
            t, r = pose_error(np.array(f["pose_c2w"]), gt[f["name"]])
            assert t == pytest.approx(f["translation_m"], abs=1e-9) and r == pytest.approx(f["rotation_deg"], abs=1e-6)


def test_timing_statistics_against_hand_computed_values() -> None:
    """Totals 1..100 ms: mean 50.5, p50 50.5, p90 90.1, p95 95.05, p99 99.01, max 100 (linear interpolation)."""
    outs = [FrameOutcome(record=None, result=None, times_ms={s: float(v) for s in STAGES}) for v in range(1, 101)]
    t = timing_summary(outs)
    assert t["total"] == pytest.approx(
        {"mean": 50.5, "p50": 50.5, "p90": 90.1, "p95": 95.05, "p99": 99.01, "max": 100.0}
    )
    outs = [
        FrameOutcome(record=None, result=None, times_ms={**{s: 0.0 for s in STAGES}, "pnp": v})
        for v in (4.0, 1.0, 3.0, 2.0)
    ]
    assert timing_summary(outs)["pnp"] == pytest.approx(
        {"mean": 2.5, "p50": 2.5, "p90": 3.7, "p95": 3.85, "p99": 3.97, "max": 4.0}
    )


def test_geometry_through_crop_and_resize_is_exact(tiny, tmp_path: Path) -> None:
    """An oracle graph that outputs the true coordinates of one view: the pose comes back to < 1 mm.

    The frame is captured at twice the bundle's size and a wider aspect, so the intrinsics go through
    the centre crop and the resize; any half-pixel or offset slip shows up as centimetres here.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from acesplat.core.bundle import ROLE_SCR_FP32, describe_file, write_manifest
    from tests.test_edge_scene import ROOM, _texture, camera_poses, render

    rng = np.random.default_rng(5)
    textures = [_texture(rng) for _ in range(6)]
    T = camera_poses(6, 0.3, rng)[2]
    k_in = Intrinsics(70.0, 70.0, 39.5, 31.5, 80, 64)
    _, depth = render(textures, T, k_in)
    from acesplat.core.geometry import transform_points
    from acesplat.core.grid import cell_centers

    c = cell_centers(8, 10)
    z = depth[c[:, 1].astype(int), c[:, 0].astype(int)]
    # the cell centre is between pixels; use the exact ray depth there by re-rendering at the centres
    X = []
    for u, v in c:
        k1 = Intrinsics(k_in.fx, k_in.fy, k_in.cx - u, k_in.cy - v, 1, 1)
        _, d1 = render(textures, T, k1)
        X.append(transform_points(T, k_in.unproject(np.array([[u, v]]), d1.reshape(1)))[0])
    X = np.asarray(X, np.float32).reshape(8, 10, 3)
    assert np.all(np.abs(X).max() < ROOM.max() + 1e-3) and z.shape == (80,)
    coords = numpy_helper.from_array(np.moveaxis(X, -1, 0)[None].copy(), "oracle")
    graph = helper.make_graph(
        [
            helper.make_node("ReduceMean", ["gray"], ["m"], keepdims=1),
            helper.make_node("Mul", ["m", "zero"], ["z"]),
            helper.make_node("Add", ["oracle", "z"], ["coords"]),
        ],
        "oracle",
        [helper.make_tensor_value_info("gray", TensorProto.FLOAT, [1, 1, 64, 80])],
        [helper.make_tensor_value_info("coords", TensorProto.FLOAT, [1, 3, 8, 10])],
        [coords, numpy_helper.from_array(np.zeros((1, 1, 1, 1), np.float32), "zero")],
    )
    root = tmp_path / "oracle"
    root.mkdir()
    onnx.save(
        helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8), str(root / "scr.onnx")
    )
    write_manifest(
        root, {"scr": {"input_size": [64, 80], "output_stride": 8}}, [describe_file(root, "scr.onnx", ROLE_SCR_FP32)]
    )
    loc = EdgeLocalizer(load_bundle(root), "fp32", threads=1, pnp=PnPSettings(min_inliers=20))
    # capture: 128 x 200 (wider), whose centre 128 x 160 crop downsampled 2x is exactly k_in
    k_cap = Intrinsics(2 * k_in.fx, 2 * k_in.fy, (k_in.cx + 0.5) * 2 - 0.5 + 20, (k_in.cy + 0.5) * 2 - 0.5, 200, 128)
    rgb, _ = render(textures, T, k_cap)
    out = loc.localize(SourceFrame(rgb, 1.0, k_cap, 7))
    t_err, r_err = pose_error(out.result.T_c2w, T)
    assert (
        out.record.state == TrackingState.TRACKING and out.record.frame_id == 7 and out.record.timestamp_us == 1_000_000
    )
    assert t_err < 1e-3 and r_err < 0.05


def test_localize_json_lines_and_ctrl_c(tiny, tmp_path: Path, monkeypatch) -> None:
    """Ctrl-C during the third frame: a clean summary, exit 0, and only whole lines in the log."""
    import edge.runtime as rt

    calls = {"n": 0}
    real = rt.EdgeLocalizer.localize

    def interrupting(self, frame, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(self, frame, *a, **k)

    monkeypatch.setattr(rt.EdgeLocalizer, "localize", interrupting)
    log = tmp_path / "poses.jsonl"
    summary = tmp_path / "s.json"
    r = CliRunner().invoke(
        app,
        [
            "localize",
            str(tiny["bundle"]),
            "--source",
            f"replay:{tiny['scene']}/test",
            "--json-lines",
            str(log),
            "--threads",
            "1",
            "--json",
            str(summary),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "interrupted" in r.output
    text = log.read_text()
    assert text.endswith("\n")
    lines = [json.loads(ln) for ln in text.splitlines()]
    assert len(lines) == 2 and [ln["frame_id"] for ln in lines] == [0, 1]
    assert set(lines[0]) >= {"timestamp_us", "frame_id", "T_c2w", "inliers", "state", "ms"}
    assert set(lines[0]["ms"]) == set(STAGES)
    s = json.loads(summary.read_text())
    assert s["interrupted"] and s["frames"] == 2


def test_json_lines_never_keeps_half_a_line(tmp_path: Path, monkeypatch) -> None:
    import os

    import edge.outputs as outputs

    w = outputs.JsonLinesWriter(tmp_path / "a.jsonl")
    w.write({"frame": 1})
    real_write = os.write

    def half_then_fail(fd, data):
        real_write(fd, data[: len(data) // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(outputs.os, "write", half_then_fail)
    with pytest.raises(OSError):
        w.write({"frame": 2, "padding": "x" * 50})
    monkeypatch.setattr(outputs.os, "write", real_write)
    w.close()
    assert (tmp_path / "a.jsonl").read_text() == '{"frame":1}\n'


def test_unreadable_frames_are_skipped_and_counted(tiny, localizer, tmp_path: Path) -> None:
    split = tmp_path / "scene" / "test"
    shutil.copytree(Path(tiny["scene"]) / "test", split)
    (split / "rgb" / "0001.png").write_bytes(b"\x89PNG garbage")
    s = replay_split(localizer, tmp_path / "scene", "test")
    assert s["skipped"] == 1 and "0001.png" in s["skipped_frames"][0]
    assert s["frames"] == 3 and s["localized"] == 3


def test_wrong_image_size_is_a_one_line_error(tiny, tmp_path: Path) -> None:
    calib = tmp_path / "cam.json"
    calib.write_text(json.dumps({"fx": 500, "fy": 500, "cx": 320, "cy": 240, "width": 640, "height": 480}))
    folder = tmp_path / "imgs"
    folder.mkdir()
    shutil.copy(Path(tiny["scene"]) / "test" / "rgb" / "0000.png", folder / "a.png")  # 80 x 64: aspect 5:4, not 4:3
    r = CliRunner().invoke(
        app, ["localize", str(tiny["bundle"]), "--source", f"replay:{folder}", "--intrinsics", str(calib)]
    )
    assert r.exit_code == 2
    assert "80x64 but the calibration is for 640x480" in r.output and "Traceback" not in r.output


def test_missing_source_and_missing_intrinsics(tiny, tmp_path: Path) -> None:
    runner = CliRunner()
    for src, msg in (
        (f"replay:{tmp_path}/none", "does not exist"),
        ("video:/no/such.mp4", "needs --intrinsics"),
        ("tape:3", "unknown source"),
    ):
        r = runner.invoke(app, ["localize", str(tiny["bundle"]), "--source", src])
        assert r.exit_code == 2 and msg in r.output, (src, r.output)
    folder = tmp_path / "imgs"
    folder.mkdir()
    shutil.copy(Path(tiny["scene"]) / "test" / "rgb" / "0000.png", folder / "a.png")
    r = runner.invoke(app, ["localize", str(tiny["bundle"]), "--source", f"replay:{folder}"])
    assert r.exit_code == 2 and "--intrinsics" in r.output


class FakeCapture:
    """cv2.VideoCapture stand-in: frames from a list; the device 'vanishes' after ``fail_after`` reads."""

    def __init__(self, frames: list[np.ndarray], script: dict) -> None:
        self.frames, self.script = frames, script
        self.opened = True

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return self.opened

    def read(self):
        s = self.script
        s["reads"] += 1
        if s["reads"] == s["fail_at"]:
            return False, None
        return True, self.frames[s["reads"] % len(self.frames)].copy()

    def release(self) -> None:
        self.opened = False


def test_camera_that_disappears_is_reconnected_and_the_gap_counted(tiny, localizer) -> None:
    import cv2

    from acesplat.core.scene import read_split
    from edge.calibration import CameraCalibration

    frames = [cv2.cvtColor(f.load_rgb(), cv2.COLOR_RGB2BGR) for f in read_split(tiny["scene"], "test").frames]
    script = {"reads": 0, "fail_at": 4, "opens": 0}

    def opener(index: int):
        script["opens"] += 1
        cap = FakeCapture(frames, script)
        cap.opened = script["opens"] not in (2, 3)  # the first two reconnect attempts find nothing
        return cap

    K = read_split(tiny["scene"], "test").frames[0].intrinsics.K
    src = CameraSource(0, CameraCalibration(K=K, size=(80, 64)), opener=opener)
    events, outs = [], []
    stats = run_loop(src, localizer, outs.append, events.append, max_frames=8, backoff=(0.01, 0.02))
    kinds = [e.kind for e in events]
    assert kinds.count("disconnected") == 1 and kinds.count("reconnected") == 1
    assert stats.disconnects == 1 and stats.reconnects == 1
    assert stats.gap_s >= 0.01 + 0.02 + 0.02  # three waits of the backoff before the fourth open works
    assert stats.frames == 8 and script["opens"] == 4
    assert sum(o.record.state == TrackingState.TRACKING for o in outs) >= 6


def test_slow_processing_drops_old_frames_and_keeps_the_latest(tiny, localizer) -> None:
    """A live source faster than the consumer: frames are replaced in the slot (counted), never queued."""
    import time

    from acesplat.core.scene import read_split

    f0 = read_split(tiny["scene"], "test").frames[0]
    rgb = f0.load_rgb()

    class FastLive:
        live = True
        description = "fast"

        def __init__(self) -> None:
            self.i = 0

        def read(self):
            time.sleep(0.002)
            self.i += 1
            return None if self.i > 400 else SourceFrame(rgb, time.monotonic(), f0.intrinsics, self.i)

        def reconnect(self) -> None: ...

        def close(self) -> None: ...

    def slow(out) -> None:
        time.sleep(0.03)

    stats = run_loop(FastLive(), localizer, slow, max_frames=5)
    assert stats.frames == 5 and stats.dropped > 5


def test_record_reads_back_through_replay(tiny, tmp_path: Path) -> None:
    r = CliRunner().invoke(
        app, ["record", str(tmp_path / "rec"), "--source", f"replay:{tiny['scene']}/test", "--frames", "3"]
    )
    assert r.exit_code == 0, r.output
    src = ReplaySource(tmp_path / "rec")
    orig = ReplaySource(Path(tiny["scene"]) / "test")
    got = [src.read() for _ in range(3)]
    assert src.read() is None and len(src) == 3
    stamps = (tmp_path / "rec" / "timestamps.txt").read_text().split()
    for g in got:
        o = orig.read()
        np.testing.assert_array_equal(g.image, o.image)
        np.testing.assert_allclose(g.intrinsics.K, o.intrinsics.K)
        np.testing.assert_allclose(g.gt_pose, o.gt_pose, atol=1e-9)
        assert float(stamps[2 * g.frame_id + 1]) == pytest.approx(g.timestamp)
    r = CliRunner().invoke(app, ["record", str(tmp_path / "rec"), "--source", f"replay:{tiny['scene']}/test"])
    assert r.exit_code == 2 and "not empty" in r.output


def test_profile_compare_json(tiny, tmp_path: Path) -> None:
    out = tmp_path / "p.json"
    r = CliRunner().invoke(
        app,
        [
            "profile",
            str(tiny["bundle"]),
            "--frames",
            "3",
            "--warmup",
            "1",
            "--compare",
            "--threads",
            "1",
            "--json",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    p = json.loads(out.read_text())
    # the INT8 graph is the one the device check picks on this CPU
    assert p["precision"][0] == "fp32" and p["precision"][1] in INT8_PRECISIONS and p["input_size"] == [64, 80]
    for prec in p["precision"]:
        assert set(p["stages"][prec]) == set(STAGES)
        assert p["fps"][prec] == pytest.approx(1000.0 / p["stages"][prec]["total"]["mean"])
        assert all(set(v) == STAT_KEYS for v in p["stages"][prec].values())
    assert p["frames"] == 3 and p["warmup_frames"] == 1
    h = p["header"]
    assert h["threads"] == 1 and h["cpu"] and len(h["model_sha256"][p["precision"][1]]) == 64
    assert h["encoder_rank"] is None  # an exact encoder
    assert "cpu:" in r.output and "sha256" in r.output


def test_tampered_bundle_is_refused_by_the_edge(tiny, tmp_path: Path) -> None:
    b = tmp_path / "b"
    shutil.copytree(tiny["bundle"], b)
    data = bytearray((b / "scr.onnx").read_bytes())
    data[len(data) // 2] ^= 0x01
    (b / "scr.onnx").write_bytes(bytes(data))
    r = CliRunner().invoke(app, ["replay", str(b), str(tiny["scene"])])
    assert r.exit_code == 2 and "does not match the manifest" in r.output


def test_pose_sink_latest_wins() -> None:
    from acesplat.core.pose import PoseRecord
    from edge.outputs import AsyncPoseSink

    got = []
    gate, busy = threading.Event(), threading.Event()

    def slow(rec) -> None:
        busy.set()
        gate.wait(5.0)
        got.append(rec.frame_id)

    sink = AsyncPoseSink(slow)
    sink.send(PoseRecord(0, frame_id=0))
    assert busy.wait(5.0)  # the consumer is now blocked on frame 0
    for i in range(1, 6):
        sink.send(PoseRecord(i, frame_id=i))
    gate.set()
    sink.close()
    assert got == [0, 5] and sink.dropped == 4


def test_localize_sends_poses_over_the_firmware_bridge(tiny, tmp_path: Path) -> None:
    """--serial with pyserial's loop:// port: every pose is handed to the bridge's non-blocking sink."""
    summary = tmp_path / "s.json"
    r = CliRunner().invoke(
        app,
        [
            "localize",
            str(tiny["bundle"]),
            "--source",
            f"replay:{tiny['scene']}/test",
            "--quiet",
            "--threads",
            "1",
            "--serial",
            "loop://",
            "--json",
            str(summary),
        ],
    )
    assert r.exit_code == 0, r.output
    s = json.loads(summary.read_text())
    assert s["frames"] == 4 and s["bridge"]["submitted"] == 4
    # a pose still waiting when the sink closes is neither sent nor counted as dropped by the bridge
    assert 1 <= s["bridge"]["sent"] + s["bridge"]["dropped"] <= 4 and s["bridge"]["sent"] >= 1


def test_paced_localizer_returns_no_earlier_than_the_budget(tiny) -> None:
    import time

    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", threads=1, pace_ms=150.0)
    frame = ReplaySource(Path(tiny["scene"]) / "test").read()
    t0 = time.perf_counter()
    out = loc.localize(frame, 0.0, t0)
    assert out.record.frame_id == frame.frame_id
    assert time.perf_counter() - t0 >= 0.149  # the budget counts from the capture start


def test_taps_see_every_frame_with_its_arrays_and_the_loop_events(tiny) -> None:
    """A tap gets the frame before and after localization, with the network's coordinates, and the loop's events;
    features only when it declares it needs them and the graph has them."""
    from edge.runtime import FrameTap

    class Recorder(FrameTap):
        def __init__(self, needs_features: bool) -> None:
            self.needs_features = needs_features
            self.calls: list = []

        def before_frame(self, frame) -> None:
            self.calls.append(("before", frame.frame_id))

        def on_frame(self, out) -> None:
            self.calls.append(("frame", out.record.frame_id, out.coords.shape, out.features is not None))

        def on_event(self, event) -> None:
            self.calls.append(("event", event.kind))

    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", threads=1)
    plain, feats = Recorder(False), Recorder(True)
    loc.add_tap(plain)
    loc.add_tap(feats)
    with pytest.raises(TypeError):
        loc.add_tap(object())
    stats = run_loop(ReplaySource(Path(tiny["scene"]) / "test"), loc, lambda out: None)
    assert [c[0] for c in plain.calls] == ["before", "frame"] * stats.frames
    assert all(len(c[2]) == 3 and c[2][2] == 3 for c in plain.calls if c[0] == "frame")
    with_features = [c[3] for c in feats.calls if c[0] == "frame"]
    assert with_features == [loc.session.has_features] * stats.frames


def test_scr_on_a_smaller_copy_keeps_the_full_frame_and_taps_needing_features_get_the_full_size(tiny) -> None:
    """With a smaller SCR size (as --align sets it) the network sees a resized copy with its own intrinsics and the
    frame at the bundle's size rides along for the alignment; a tap that needs features gets the bundle's size."""
    from edge.runtime import FrameTap

    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", threads=1)
    assert loc.scr_size == loc.input_size == (64, 80)  # no --align: the bundle's size
    loc.scr_size = (56, 72)
    frame = ReplaySource(Path(tiny["scene"]) / "test").read()
    p = loc.prepare(frame)
    assert p.gray.shape == (56, 72) and p.coords.shape == (7, 9, 3) and p.view is not None
    full_gray, full_intr = p.view
    assert full_gray.shape == (64, 80) and (full_intr.width, full_intr.height) == (80, 64)
    assert p.intr == full_intr.resized(72, 56)

    class NeedsFeatures(FrameTap):
        needs_features = True

    loc.add_tap(NeedsFeatures())
    q = loc.prepare(frame)
    assert q.gray.shape == (64, 80) and q.view is None and q.coords.shape == (8, 10, 3)


def test_out_of_order_and_repeated_timestamps_are_refused_and_counted(tiny, localizer) -> None:
    """A frame whose timestamp does not move forward is not localized (tracking's motion model needs time to
    advance): one event line each, counted apart in the summary, and the run goes on."""
    from acesplat.core.scene import read_split

    frames = read_split(tiny["scene"], "test").frames[:4]
    stamps = [1.0, 2.0, 2.0, 1.5, 3.0, 4.0]  # a repeat, then one from the past
    which = [0, 1, 1, 2, 2, 3]

    class Jumbled:
        live = False
        description = "jumbled"

        def __init__(self) -> None:
            self.i = 0

        def read(self):
            if self.i >= len(stamps):
                return None
            f = frames[which[self.i]]
            out = SourceFrame(f.load_rgb(), stamps[self.i], f.intrinsics, self.i, f"f{self.i}")
            self.i += 1
            return out

        def reconnect(self) -> None: ...

        def close(self) -> None: ...

    outs, events = [], []
    stats = run_loop(Jumbled(), localizer, outs.append, events.append)
    assert [o.record.frame_id for o in outs] == [0, 1, 4, 5]
    assert (stats.frames, stats.repeated, stats.out_of_order) == (4, 1, 1)
    lines = [e.detail for e in events if e.kind == "out_of_order"]
    assert len(lines) == 2 and "f2: repeated timestamp" in lines[0] and "f3: out of order" in lines[1]
    d = stats.as_dict()
    assert (d["repeated"], d["out_of_order"]) == (1, 1)
