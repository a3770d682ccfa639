"""The OAK source against the installed depthai: every call checked against the real pybind11 signatures.

What works without a device is the real thing here: ``MessageQueue`` (get with a timeout, close,
``QueueException``), ``ImgFrame``, ``CalibrationHandler``, the enums, and ``Pipeline()`` failing to
find a device. What needs a device (``Pipeline`` with a device, ``node.Camera``, ``Node.Output``,
``Device``) is faked, and each fake method first binds its arguments against the overloads parsed
from the real method's ``__doc__`` (names, positional/keyword, argument types, return type), so
the fake rejects what the real binding rejects.
"""

from __future__ import annotations

import ast
import builtins
import datetime
import functools
import importlib
import inspect
import re
import threading
import time
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from acesplat.core.errors import InputError
from acesplat.core.pose import TrackingState
from edge.calibration import CameraCalibration
from edge.loop import _Events, _read, run_loop
from edge.oak import OakSource, resize_intrinsics
from edge.sources import SourceDisconnected, SourceOptions, open_source

ROOT = Path(__file__).resolve().parents[1]
K0 = np.array([[1500.0, 0, 955.3], [0, 1498.0, 541.7], [0, 0, 1]])
DIST = [0.01 * (i + 1) for i in range(14)]


@pytest.fixture(scope="module")
def dai():
    return pytest.importorskip("depthai", reason="depthai is not installed (it is in the 'test' extra)")


# ------------------------------------------------------------------------- real signatures from __doc__
def _split_top(text: str) -> list[str]:
    """Split at commas outside brackets and quotes."""
    parts, depth, quote, cur = [], 0, None, ""
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "([{<":
            depth += 1
        elif ch in ")]}>":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append(cur.strip())
            cur = ""
            continue
        cur += ch
    if cur.strip():
        parts.append(cur.strip())
    return parts


class Overload:
    """One pybind11 overload: a signature without ``self``, each parameter's annotation, the return annotation."""

    def __init__(self, params: str, ret: str) -> None:
        self.annotations: dict[str, str] = {}
        out: list[inspect.Parameter] = []
        kind = inspect.Parameter.POSITIONAL_OR_KEYWORD
        for i, p in enumerate(_split_top(params)):
            if p == "/":
                out = [q.replace(kind=inspect.Parameter.POSITIONAL_ONLY) for q in out]
                continue
            if p == "*":
                kind = inspect.Parameter.KEYWORD_ONLY
                continue
            if p.startswith("**"):
                out.append(inspect.Parameter(p[2:].split(":")[0], inspect.Parameter.VAR_KEYWORD))
                continue
            if p.startswith("*"):
                out.append(inspect.Parameter(p[1:].split(":")[0], inspect.Parameter.VAR_POSITIONAL))
                kind = inspect.Parameter.KEYWORD_ONLY
                continue
            head, _, default = p.partition(" = ")
            name, _, ann = head.partition(": ")
            if i == 0 and name == "self":
                continue
            self.annotations[name] = ann
            # pybind11 shows unnamed arguments as argN: they cannot be passed by keyword
            k = inspect.Parameter.POSITIONAL_ONLY if re.fullmatch(r"arg\d+", name) else kind
            out.append(inspect.Parameter(name, k, default=default if default else inspect.Parameter.empty))
        self.signature = inspect.Signature(out)
        self.ret = ret

    def __repr__(self) -> str:
        return f"{self.signature} -> {self.ret}"


def real_overloads(func: Any) -> list[Overload]:
    """The overloads pybind11 lists in ``func.__doc__`` (numbered when overloaded)."""
    name = func.__name__
    lines = [ln.strip() for ln in (func.__doc__ or "").splitlines()]
    pat = re.compile(rf"^(\d+\. )?{re.escape(name)}\((.*)\)(?: -> (.+))?$")
    found = [(m[1], m[2], m[3] or "") for m in map(pat.match, lines) if m]
    numbered = [f for f in found if f[0]]
    chosen = numbered or found[:1]
    assert chosen, f"no signature in the docstring of {func!r}"
    return [Overload(params, ret) for _, params, ret in chosen]


def _resolve(ann: str) -> type:
    mod_name, *attrs = ann.split(".")
    obj: Any = importlib.import_module(mod_name)
    for a in attrs:
        obj = getattr(obj, a)
    assert isinstance(obj, type), ann
    return obj


def _is_instance(value: Any, cls: type) -> bool:
    """A real instance, or an instance of a fake that mirrors ``cls`` (or a subclass of it)."""
    real = getattr(type(value), "__real__", None)
    return isinstance(value, cls) or (real is not None and issubclass(real, cls))


def accepts(ann: str, value: Any) -> bool:
    """Would pybind11 convert ``value`` to ``ann``? (The conversions depthai's bindings perform, observed.)"""
    ann = ann.strip()
    if ann in ("object", ""):
        return True
    if m := re.fullmatch(r"Optional\[(.*)\]", ann):
        return value is None or accepts(m[1], value)
    if m := re.fullmatch(r"(tuple|list)\[(.*)\]", ann):
        if not isinstance(value, (tuple, list)):
            return False
        items = _split_top(m[2])
        if m[1] == "list":
            return all(accepts(items[0], v) for v in value)
        return len(value) == len(items) and all(accepts(a, v) for a, v in zip(items, value))
    if ann == "int":
        return isinstance(value, int)
    if ann == "float":
        return isinstance(value, (int, float))
    if ann == "bool":
        return value is None or isinstance(value, (bool, int, np.bool_))
    if ann == "str":
        return isinstance(value, str)
    if ann == "datetime.timedelta":  # the chrono caster takes a timedelta or float seconds, not an int
        return isinstance(value, datetime.timedelta) or type(value) is float
    return _is_instance(value, _resolve(ann))


def bind_real(overloads: list[Overload], args: tuple, kwargs: dict) -> tuple[int, inspect.BoundArguments]:
    """(overload index, bound arguments) of the first overload the call fits, else TypeError as pybind11 raises."""
    for i, ov in enumerate(overloads):
        try:
            bound = ov.signature.bind(*args, **kwargs)
        except TypeError:
            continue
        if all(accepts(ov.annotations.get(k, ""), v) for k, v in bound.arguments.items() if k in ov.annotations):
            return i, bound
    raise TypeError(f"incompatible function arguments {args} {kwargs}; the real overloads are {overloads}")


def returns(ann: str, value: Any) -> bool:
    ann = ann.strip()
    if ann == "None":
        return value is None
    if ann in ("bool", "int", "float", "str"):
        return accepts(ann, value)
    return _is_instance(value, _resolve(ann))


def mirrors(real: type):
    """Class decorator: the fake stands for ``real``; each public method (and ``__init__``) is checked against the
    real method's overloads before it runs, and its result against the overload's return type."""

    def wrap(cls: type) -> type:
        cls.__real__ = real
        for name, impl in list(vars(cls).items()):
            if not callable(impl) or (name.startswith("_") and name != "__init__"):
                continue
            assert hasattr(real, name), f"{real.__qualname__} has no {name}: the fake must not invent methods"
            overloads = real_overloads(getattr(real, name))

            def checked(self, *args, __impl=impl, __name=name, __ov=overloads, **kwargs):
                i, bound = bind_real(__ov, args, kwargs)
                self._world.calls.append((f"{cls.__name__}.{__name}", i, dict(bound.arguments)))
                result = __impl(self, *args, **kwargs)
                ret = "None" if __name == "__init__" else __ov[i].ret
                assert returns(ret, result), f"fake {real.__qualname__}.{__name} returned {result!r}, real gives {ret}"
                return result

            checked.__checked__ = overloads
            checked.__name__ = name
            setattr(cls, name, checked)
        return cls

    return wrap


# ------------------------------------------------------------------------------------------ the fake
class FakeDai:
    """depthai with a scripted device: real enums, MessageQueue, ImgFrame and CalibrationHandler; Pipeline,
    node.Camera, Node.Output and Device are fakes whose calls are checked against the real signatures.

    ``frames_per_start``: after that many frames the device is lost (``loss``: 'close' closes the queue as an
    unplug does, 'silent' stops sending); ``stream``: a thread sends frames, else ``push()`` sends one.
    """

    def __init__(
        self,
        dai: Any,
        calibration: Any = None,
        no_device: bool = False,
        stream: bool = False,
        frames_per_start: int | None = None,
        loss: str = "close",
    ) -> None:
        self.real = dai
        self.no_device = no_device
        self.stream = stream
        self.frames_per_start = frames_per_start
        self.loss = loss
        self.calls: list[tuple[str, int, dict]] = []
        self.starts = 0
        self.seq = 0
        self.queue: Any = None
        self.size = (0, 0)
        self.running_error: BaseException | None = None
        self.pipelines: list[Any] = []
        if calibration is None:
            calibration = dai.CalibrationHandler()
            calibration.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, K0.tolist(), 1920, 1080)
            calibration.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, DIST)
        self.calibration = calibration
        world = self

        @mirrors(dai.Device)
        class Device:
            _world = world
            _closed = False

            def readCalibration(self):  # noqa: N802
                return world.calibration

            def close(self) -> None:
                self._closed = True

        @mirrors(dai.Node.Output)
        class Output:
            _world = world

            def createOutputQueue(self, maxSize=16, blocking=False):  # noqa: N802, N803
                world.queue = dai.MessageQueue("fake-camera", maxSize, blocking)
                return world.queue

        @mirrors(dai.node.Camera)
        class Camera:
            _world = world

            def build(self, boardSocket=None, sensorResolution=None, sensorFps=None):  # noqa: N803
                self.socket = boardSocket
                return self

            def requestOutput(self, size, type=None, resizeMode=None, fps=None, **_):  # noqa: N802, N803, A002
                world.size = tuple(size)
                world.frame_type = type
                return Output()

        @mirrors(dai.Pipeline)
        class Pipeline:
            _world = world

            def __init__(self, createImplicitDevice=True) -> None:  # noqa: N803
                if world.no_device:
                    raise RuntimeError("No available devices")
                self.device = Device()
                self.running = False
                self.sent = 0
                world.pipelines.append(self)

            def create(self, arg0, *args, **kwargs):
                assert arg0 is dai.node.Camera
                return Camera()

            def start(self) -> None:
                world.starts += 1
                self.running = True
                if world.stream:
                    threading.Thread(target=self._produce, daemon=True).start()

            def isRunning(self) -> bool:  # noqa: N802
                err, world.running_error = world.running_error, None
                if err is not None:  # once, as a link error reaches one call
                    raise err
                return self.running

            def stop(self) -> None:
                self.running = False

            def getDefaultDevice(self):  # noqa: N802
                return self.device

            def _produce(self) -> None:
                while self.running and world.queue is not None and not world.queue.isClosed():
                    if not self._send():
                        return
                    time.sleep(0.005)

            def _send(self) -> bool:
                if world.frames_per_start is not None and self.sent >= world.frames_per_start:
                    if world.loss == "close":
                        world.queue.close()
                    return False
                world.seq += 1
                self.sent += 1
                w, h = world.size
                bgr = np.zeros((h, w, 3), np.uint8)
                bgr[..., 0] = 255  # blue in BGR
                frame = dai.ImgFrame()
                frame.setCvFrame(bgr, dai.ImgFrame.Type.BGR888i)
                frame.setTimestamp(datetime.timedelta(milliseconds=33 * world.seq))
                frame.setSequenceNum(world.seq)
                world.queue.send(frame)
                return True

        self.classes = (Device, Output, Camera, Pipeline)
        self.Pipeline = Pipeline
        self.node = types.SimpleNamespace(Camera=dai.node.Camera)
        self.CameraBoardSocket = dai.CameraBoardSocket
        self.ImgResizeMode = dai.ImgResizeMode
        self.ImgFrame = dai.ImgFrame
        self.MessageQueue = dai.MessageQueue

    def push(self) -> bool:
        return self.pipelines[-1]._send()

    def called(self) -> set[str]:
        return {name for name, _, _ in self.calls}


# ------------------------------------------------------------------- the checker and the fake themselves
def _verdict(call) -> str:
    try:
        call()
    except TypeError:
        return "rejected"
    except RuntimeError:
        return "accepted"  # the arguments converted; the call then failed for another reason
    return "accepted"


def test_signature_checker_agrees_with_the_real_bindings(dai) -> None:
    """Every case is called for real and through the checker: both accept or both reject."""
    td = datetime.timedelta(milliseconds=1)
    A = dai.CameraBoardSocket.CAM_A
    img = np.zeros((4, 4, 3), np.uint8)
    cases = [
        (dai.MessageQueue, "__init__", (), {}),
        (dai.MessageQueue, "__init__", ("q", 1, False), {}),
        (dai.MessageQueue, "__init__", ("q",), {"maxSize": 1, "blocking": False}),
        (dai.MessageQueue, "__init__", ("q",), {"max_size": 1}),
        (dai.MessageQueue, "__init__", ("q", 1.5, False), {}),
        (dai.MessageQueue, "__init__", ("q", 1, "x"), {}),
        (dai.MessageQueue, "__init__", ("q", True, 1), {}),
        (dai.MessageQueue, "get", (), {}),
        (dai.MessageQueue, "get", (td,), {}),
        (dai.MessageQueue, "get", (), {"timeout": td}),
        (dai.MessageQueue, "get", (0.001,), {}),
        (dai.MessageQueue, "get", (1,), {}),
        (dai.MessageQueue, "get", (), {"timeout_s": 0.001}),
        (dai.MessageQueue, "get", (td, td), {}),
        (dai.CalibrationHandler, "getDefaultIntrinsics", (A,), {}),
        (dai.CalibrationHandler, "getDefaultIntrinsics", (), {"cameraId": A}),
        (dai.CalibrationHandler, "getDefaultIntrinsics", (), {"socket": A}),
        (dai.CalibrationHandler, "getDefaultIntrinsics", ("CAM_A",), {}),
        (dai.CalibrationHandler, "getDistortionCoefficients", (A,), {}),
        (dai.CalibrationHandler, "setCameraIntrinsics", (A, K0.tolist(), 1920, 1080), {}),
        (dai.CalibrationHandler, "setCameraIntrinsics", (A, K0.tolist(), 1920.5, 1080), {}),
        (dai.ImgFrame, "setSequenceNum", (3,), {}),
        (dai.ImgFrame, "setSequenceNum", (3.5,), {}),
        (dai.ImgFrame, "setCvFrame", (img, dai.ImgFrame.Type.BGR888i), {}),
        (dai.ImgFrame, "setCvFrame", (img, "BGR888i"), {}),
        (dai.Pipeline, "__init__", (False,), {}),
        (dai.Pipeline, "__init__", (), {"createImplicitDevice": False}),
        (dai.Pipeline, "__init__", (), {"create_implicit_device": False}),
    ]
    for cls, name, args, kwargs in cases:
        if name == "__init__":
            real_call = functools.partial(cls, *args, **kwargs)
        else:
            obj = dai.MessageQueue("q", 4, False) if cls is dai.MessageQueue else cls()
            if cls is dai.MessageQueue:
                obj.send(dai.ImgFrame())  # so a get() without timeout returns at once
            real_call = functools.partial(getattr(obj, name), *args, **kwargs)
        ours = _verdict(functools.partial(bind_real, real_overloads(getattr(cls, name)), args, kwargs))
        assert ours == _verdict(real_call), (cls.__name__, name, args, kwargs)


def test_fake_methods_exist_on_the_real_classes_and_are_all_checked(dai) -> None:
    fake = FakeDai(dai)
    for cls in fake.classes:
        public = [n for n, v in vars(cls).items() if callable(v) and (not n.startswith("_") or n == "__init__")]
        assert public, cls
        for n in public:
            assert hasattr(cls.__real__, n) and getattr(cls, n).__checked__, (cls.__name__, n)


def test_fake_rejects_what_the_real_library_rejects(dai) -> None:
    """The spellings the source used before (snake_case keywords, a get without timeout) do not get through."""
    fake = FakeDai(dai)
    cam = fake.Pipeline().create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
    with pytest.raises(TypeError, match="incompatible"):
        cam.requestOutput((320, 240), type=dai.ImgFrame.Type.BGR888i, resize_mode=dai.ImgResizeMode.CROP, fps=30.0)
    with pytest.raises(TypeError, match="incompatible"):
        cam.requestOutput((320, 240), resizeMode="CROP")
    with pytest.raises(TypeError, match="incompatible"):
        cam.build("CAM_A")
    out = cam.requestOutput((320, 240), type=dai.ImgFrame.Type.BGR888i, resizeMode=dai.ImgResizeMode.CROP, fps=30.0)
    with pytest.raises(TypeError, match="incompatible"):
        out.createOutputQueue(max_size=1)
    q = out.createOutputQueue(maxSize=1, blocking=False)
    assert type(q) is dai.MessageQueue and q.getMaxSize() == 1
    with pytest.raises(TypeError):  # the real queue's own binding
        q.get(timeout_s=0.1)


# --------------------------------------------------------------------------- what the source calls
# methods the source calls on objects that are not depthai's (numpy, cv2, its own, calibration override)
NOT_DEPTHAI = {"asarray", "cvtColor", "intrinsics_for", "total_seconds", "upper", "timedelta", "_start", "_stop"}
NOT_DEPTHAI |= {"_device_errors"}
# called on real depthai objects (their own bindings check the arguments)
ON_REAL_OBJECTS = {
    "get": "MessageQueue",
    "getCvFrame": "ImgFrame",
    "getTimestamp": "ImgFrame",
    "getSequenceNum": "ImgFrame",
    "getDefaultIntrinsics": "CalibrationHandler",
    "getDistortionCoefficients": "CalibrationHandler",
}


def _method_calls_in_source() -> set[str]:
    tree = ast.parse((ROOT / "edge" / "oak.py").read_text())
    return {n.func.attr for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)}


def test_every_depthai_call_the_source_makes_is_checked(dai) -> None:
    fake = FakeDai(dai)
    src = OakSource((240, 320), resize_mode="letterbox", dai=fake)
    fake.push()
    src.read()
    src.reconnect()
    src.close()
    assert src.dai.MessageQueue is dai.MessageQueue and isinstance(fake.calibration, dai.CalibrationHandler)
    checked = {name.rsplit(".", 1)[1] for name in fake.called()} - {"__init__"} | {"Pipeline"}  # dai.Pipeline()
    in_source = _method_calls_in_source() - NOT_DEPTHAI
    assert in_source == checked | set(ON_REAL_OBJECTS), in_source ^ (checked | set(ON_REAL_OBJECTS))
    for name, cls in ON_REAL_OBJECTS.items():
        assert hasattr(getattr(dai, cls), name)
    assert fake.called() == {
        "Pipeline.__init__",
        "Pipeline.create",
        "Camera.build",
        "Camera.requestOutput",
        "Output.createOutputQueue",
        "Pipeline.start",
        "Pipeline.getDefaultDevice",
        "Device.readCalibration",
        "Pipeline.isRunning",
        "Pipeline.stop",
        "Device.close",
    }
    request = next(kw for name, i, kw in fake.calls if name == "Camera.requestOutput")
    assert request == {
        "size": (320, 240),
        "type": dai.ImgFrame.Type.BGR888i,
        "resizeMode": dai.ImgResizeMode.LETTERBOX,
        "fps": 30.0,
    }


# ------------------------------------------------------------------------------------ the behaviour
def test_oak_source_reads_real_frames_with_the_device_calibration(dai) -> None:
    fake = FakeDai(dai)
    src = OakSource((240, 320), resize_mode="crop", dai=fake)
    assert fake.size == (320, 240) and fake.queue.getMaxSize() == 1
    fake.push()
    f = src.read()
    assert f.image.shape == (240, 320, 3) and f.image[0, 0].tolist() == [0, 0, 255]  # RGB now
    assert f.timestamp == pytest.approx(0.033) and f.frame_id == 1 and f.name == "000001"
    K_dev = np.asarray(fake.calibration.getDefaultIntrinsics(dai.CameraBoardSocket.CAM_A)[0])  # float32 on the device
    assert f.intrinsics == resize_intrinsics(K_dev, (1920, 1080), (320, 240), "crop")
    np.testing.assert_allclose(f.distortion, DIST, rtol=1e-6)
    src.close()
    assert not fake.pipelines[0].running and fake.pipelines[0].device._closed


def test_oak_source_with_a_calibration_override_does_not_read_the_device(dai) -> None:
    fake = FakeDai(dai)
    K = np.array([[600.0, 0, 319.5], [0, 601.0, 239.5], [0, 0, 1]])
    calib = CameraCalibration(K=K, size=(640, 480), distortion=np.zeros(5))
    src = OakSource((240, 320), dai=fake, calibration=calib)
    assert "Device.readCalibration" not in fake.called()
    assert src.intrinsics == calib.intrinsics_for(320, 240)
    src.close()


def test_oak_without_calibration_on_the_device_names_the_way_out(dai) -> None:
    fake = FakeDai(dai, calibration=dai.CalibrationHandler())  # real handler, nothing flashed for CAM_A
    with pytest.raises(InputError, match="--intrinsics"):
        OakSource((240, 320), dai=fake)
    assert not fake.pipelines[0].running and fake.pipelines[0].device._closed


def test_oak_without_device_fake_and_real(dai, monkeypatch) -> None:
    with pytest.raises(InputError, match="no OAK device available"):
        OakSource((240, 320), dai=FakeDai(dai, no_device=True))
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK device is attached")
    monkeypatch.setenv("DEPTHAI_SEARCH_TIMEOUT", "300")  # ms; the default search waits about 10 s
    with pytest.raises(InputError, match="no OAK device available .*RuntimeError"):
        OakSource((240, 320))


def test_oak_without_depthai(monkeypatch) -> None:
    real_import = builtins.__import__

    def no_depthai(name, *a, **k):
        if name == "depthai":
            raise ImportError("No module named 'depthai'")
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_depthai)
    with pytest.raises(InputError, match=r"pip install 'acesplat-edge\[oak\]'"):
        open_source("oak", SourceOptions(input_size=(240, 320)))


def test_silent_device_times_out_into_the_source_lost_path(dai) -> None:
    fake = FakeDai(dai, frames_per_start=1, loss="silent")
    src = OakSource((240, 320), dai=fake, frame_timeout_s=0.2, first_frame_timeout_s=0.5)
    assert fake.push() and src.read().frame_id == 1
    assert not fake.push()  # the device says nothing more
    raised: list[BaseException] = []

    def read_silent() -> None:
        try:
            src.read()
        except BaseException as e:
            raised.append(e)

    t0 = time.monotonic()
    reader = threading.Thread(target=read_silent, daemon=True)  # a get() without timeout would block forever
    reader.start()
    reader.join(timeout=5.0)
    assert not reader.is_alive(), "read() blocks on a silent device"
    assert 0.15 < time.monotonic() - t0 < 2.0
    assert isinstance(raised[0], SourceDisconnected) and "no frame for 0.2 s" in str(raised[0])
    events, stop = _Events(), threading.Event()
    assert _read(src, events, stop, (0.001, 0.01)) == ("again",)  # lost, then reconnected
    assert [e.kind for e in events.drain()] == ["disconnected", "reconnected"]
    assert fake.starts == 2 and src._timeout_s == 0.5  # the first frame after a start gets the longer wait
    fake.push()
    assert src.read().frame_id == 2
    src.close()


@pytest.mark.parametrize("loss", ["closed_queue", "xlink_error"])
def test_unplugged_device_is_reconnected_and_the_capture_thread_goes_on(dai, loss: str) -> None:
    """A closed queue raises the real MessageQueue.QueueException (an Exception, not a RuntimeError); an XLink
    error is a RuntimeError subclass: both reach the loop as SourceDisconnected, and capture carries on."""
    fake = FakeDai(dai, stream=True, frames_per_start=3 if loss == "closed_queue" else None, loss="close")
    src = OakSource((240, 320), dai=fake, frame_timeout_s=0.5, first_frame_timeout_s=1.0)
    if loss == "closed_queue":
        while not fake.queue.isClosed():  # the first start's three frames are sent, then the queue closes
            time.sleep(0.01)
        with pytest.raises(dai.MessageQueue.QueueException):  # what the call raises, unhandled
            fake.queue.get(datetime.timedelta(seconds=1))
    events: list = []

    class Localizer:
        """What run_loop calls on a localizer (edge.runtime.EdgeLocalizer): localize and notify."""

        frames = 0

        def notify(self, event):
            pass

        def localize(self, frame, capture_ms, t_start):
            Localizer.frames += 1
            if loss == "xlink_error" and Localizer.frames == 2:
                fake.running_error = dai.XLinkReadError("Couldn't read data from stream: 'fake-camera'")
            time.sleep(0.01)
            return types.SimpleNamespace(record=types.SimpleNamespace(state=TrackingState.TRACKING))

    stats = run_loop(src, Localizer(), lambda out: None, on_event=events.append, max_frames=6, backoff=(0.01, 0.05))
    kinds = [e.kind for e in events]
    assert "capture_error" not in kinds, events
    assert stats.frames == 6 and stats.disconnects >= 1 and stats.reconnects >= 1, (stats, events)
    assert fake.starts >= 2
    lost = next(e for e in events if e.kind == "disconnected")
    assert ("QueueException" if loss == "closed_queue" else "XLinkReadError") in lost.detail


@pytest.mark.hardware
def test_oak_hardware() -> None:
    dai = pytest.importorskip("depthai", reason="depthai is not installed (optional extra 'oak')")
    if not dai.Device.getAllAvailableDevices():
        pytest.skip("no OAK device attached")
    src = OakSource((240, 320))
    try:
        f = src.read()
        assert f.image.shape == (240, 320, 3) and f.intrinsics.width == 320
    finally:
        src.close()
