"""`acesplat view`: the viewer scene against its arrays, the page rendered by headless Chromium, and bad input."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from acesplat.apps.cli import app
from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError
from acesplat.core.gaussians import Gaussians, logit, rgb_to_sh_dc
from acesplat.core.geometry import make_pose
from acesplat.core.ply import write_ply
from acesplat.core.viewer import (
    ViewCamera,
    ViewScene,
    build_scene,
    scene_up,
    serve,
    splat_layer,
    splat_view,
    subsample_index,
    view_kind,
    viser_pose,
)
from tests.browser import capture_until, chromium

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()
RED = (0.9, 0.1, 0.1)
"""The synthetic splat's colour, looked for in the screenshot."""


def red_cube(n: int = 3000, seed: int = 0) -> Gaussians:
    """Opaque red Gaussians filling a 1 m cube at the origin."""
    rng = np.random.default_rng(seed)
    g = Gaussians.zeros(n, sh_degree=1)
    g.means[:] = rng.uniform(-0.5, 0.5, (n, 3))
    g.log_scales[:] = math.log(0.03)
    g.opacity_logits[:] = logit(np.full(n, 0.95))
    g.sh[:, 0, :] = rgb_to_sh_dc(np.array(RED))
    return g


def looking_at_origin(eye: np.ndarray) -> np.ndarray:
    """Camera-to-world (4, 4), OpenCV axes, at ``eye`` looking at the origin with world -z as image down."""
    z = -eye / np.linalg.norm(eye)
    x = np.cross([0.0, 0.0, -1.0], z)
    x /= np.linalg.norm(x)
    return make_pose(np.stack([x, np.cross(z, x), z], axis=1), eye)


class RecordingScene:
    """The part of viser's SceneApi build_scene calls, recording each call's arguments."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple, dict]] = []

    def __getattr__(self, name: str):
        return lambda *a, **k: self.calls.append((name, a, k))

    def named(self, name: str) -> list[tuple[tuple, dict]]:
        return [(a, k) for n, a, k in self.calls if n == name]


def fake_server() -> SimpleNamespace:
    return SimpleNamespace(scene=RecordingScene(), initial_camera=SimpleNamespace())


# ----------------------------------------------------------------------------------- scene from arrays
def test_splat_layer_matches_the_parameters() -> None:
    """Covariance R diag(s^2) R^T from the quaternion and log-scales, colour from the DC term, sigmoid opacity."""
    g = Gaussians.zeros(2, sh_degree=0, dtype=np.float64)
    g.log_scales[:] = np.log([[0.1, 0.2, 0.3], [1.0, 1.0, 1.0]])
    half = math.radians(90) / 2
    g.quats[0] = [2 * math.cos(half), 0.0, 0.0, 2 * math.sin(half)]  # 90 deg about z, not normalised
    g.opacity_logits[:] = [0.0, 2.0]
    g.sh[:, 0, :] = rgb_to_sh_dc(np.array([[0.2, 0.4, 0.6], [1.5, -0.5, 0.5]]))
    layer = splat_layer(g, max_points=10)
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(layer.covariances[0], Rz @ np.diag([0.01, 0.04, 0.09]) @ Rz.T, atol=1e-7)
    np.testing.assert_allclose(layer.covariances[0], np.diag([0.04, 0.01, 0.09]), atol=1e-7)
    np.testing.assert_allclose(layer.covariances[1], np.eye(3), atol=1e-6)
    np.testing.assert_allclose(layer.rgbs, [[0.2, 0.4, 0.6], [1.0, 0.0, 0.5]], atol=1e-6)
    np.testing.assert_allclose(layer.opacities[:, 0], [0.5, 1 / (1 + math.exp(-2.0))], atol=1e-6)
    assert layer.opacities.shape == (2, 1) and layer.centers.dtype == np.float32


def test_subsampling_is_even_and_capped() -> None:
    assert subsample_index(5, 10).tolist() == [0, 1, 2, 3, 4]
    idx = subsample_index(1000, 100)
    assert len(idx) == 100 and idx[0] == 0 and idx[-1] == 999 and np.all(np.diff(idx) >= 9)
    assert len(splat_layer(red_cube(500), 77).centers) == 77


def test_viser_pose_keeps_the_opencv_camera_axes() -> None:
    """A camera at (1, 2, 3) looking along world +x with image-down world -z: viser's node rotation maps the
    frustum's local +z (forward) to world +x and local +y (down) to world -z."""
    from viser.transforms import SO3

    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: camera x, y, z in the world
    wxyz, position = viser_pose(make_pose(R, [1.0, 2.0, 3.0]))
    M = SO3(wxyz).as_matrix()
    np.testing.assert_allclose(M, R, atol=1e-12)
    np.testing.assert_allclose(M @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(M @ [0, 1, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(position, [1, 2, 3])
    with pytest.raises(ValueError, match="orthonormal"):
        viser_pose(np.diag([2.0, 1.0, 1.0, 1.0]))


def test_build_scene_sends_the_arrays_and_the_cameras() -> None:
    g = red_cube(200)
    intr = Intrinsics(50.0, 50.0, 40.0, 30.0, 80, 60)
    poses = [looking_at_origin(np.array(e, float)) for e in ((3, 0, 0), (0, 3, 0), (-3, 0, 0))]
    cams = [ViewCamera(p, intr, f"c{i}") for i, p in enumerate(poses)]
    view = ViewScene("t", splats=splat_layer(g, 1000), cameras=cams)
    server = fake_server()
    counts = build_scene(server, view)
    assert counts == {"gaussians": 200, "points": 0, "cameras": 3}
    ((args, _),) = server.scene.named("add_gaussian_splats")
    np.testing.assert_allclose(args[1], g.means)
    np.testing.assert_allclose(args[3], np.tile(RED, (200, 1)), atol=1e-6)
    frustums = server.scene.named("add_camera_frustum")
    assert len(frustums) == 3
    for (_, k), p in zip(frustums, poses):
        from viser.transforms import SO3

        np.testing.assert_allclose(SO3(k["wxyz"]).as_matrix(), p[:3, :3], atol=1e-9)
        np.testing.assert_allclose(k["position"], p[:3, 3])
        assert k["fov"] == pytest.approx(2 * math.atan(30 / 50)) and k["aspect"] == pytest.approx(80 / 60)
    ((up,), _) = server.scene.named("set_up_direction")[0]
    np.testing.assert_allclose(up, [0, 0, 1], atol=1e-9)  # image-down is world -z for all three cameras
    cam0 = server.initial_camera
    np.testing.assert_allclose(cam0.position, poses[1][:3, 3])  # the middle mapping camera
    assert np.linalg.norm(np.asarray(cam0.look_at) - poses[1][:3, 3]) > 1.0


def test_scene_up_needs_agreeing_cameras() -> None:
    intr = Intrinsics(50.0, 50.0, 40.0, 30.0, 80, 60)
    assert scene_up([]) is None
    rolled = [ViewCamera(make_pose(R, [0, 0, 0]), intr) for R in (np.eye(3), np.diag([-1.0, -1.0, 1.0]))]
    assert scene_up(rolled) is None


# ----------------------------------------------------------------------------------- the page in a browser
def canvas(im: np.ndarray) -> np.ndarray:
    """The part of an 800x600 viser page that only the 3D canvas covers (left of the control panel, below the
    software-WebGL notice, above the axes gizmo): plain background until the scene is drawn."""
    return im[160:540, 0:460]


def red_pixels(im: np.ndarray) -> int:
    b, g, r = (im[..., i].astype(int) for i in range(3))
    return int(np.sum((r > 150) & (g < 90) & (b < 90)))


def settled(ready):
    """A capture predicate: ``ready(image)`` and the canvas unchanged since the previous capture (viser fades new
    content in over seconds under software WebGL)."""
    last: list[np.ndarray] = []

    def done(im: np.ndarray) -> bool:
        still = bool(last) and float(np.abs(canvas(im).astype(float) - canvas(last[0])).mean()) < 1.0
        last[:] = [im]
        return still and ready(im)

    return done


def drawn(im: np.ndarray) -> float:
    """Fraction of the canvas that is not the page's white background."""
    return float(np.mean(np.any(canvas(im) < 235, axis=-1)))


@pytest.mark.skipif(chromium() is None, reason="no chromium binary on PATH (apt-get install chromium)")
def test_the_page_draws_the_gaussians_in_headless_chromium(tmp_path: Path) -> None:
    ply = tmp_path / "cube.ply"
    write_ply(ply, red_cube())
    from acesplat.core.ply import read_ply

    view = splat_view(read_ply(ply), "cube", None, max_points=100_000)
    server, counts = serve(view, "127.0.0.1", 0)
    try:
        im = capture_until(f"http://127.0.0.1:{server.get_port()}", lambda im: red_pixels(canvas(im)) > 3000)
    finally:
        server.stop()
    cv2.imwrite(str(tmp_path / "shot.png"), im)
    assert counts["gaussians"] == 3000
    assert canvas(im).std() > 20, f"the canvas looks blank (pixel std {canvas(im).std():.1f}): {tmp_path}"
    assert red_pixels(canvas(im)) > 3000, f"{red_pixels(canvas(im))} red pixels: the Gaussians were not drawn"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl_c", "sigterm"])
def test_the_command_prints_the_url_serves_and_stops_on_a_signal(tmp_path: Path, sig: int) -> None:
    ply = tmp_path / "cube.ply"
    write_ply(ply, red_cube(300))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    # SIGINT ignored on entry, as in a background job of a non-interactive shell: the command must still stop
    code = "import signal; signal.signal(signal.SIGINT, signal.SIG_IGN); from acesplat.apps.cli import main; main()"
    proc = subprocess.Popen(
        [sys.executable, "-P", "-c", code, "view", str(ply), "--port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
    )  # fmt: skip
    try:
        line = proc.stdout.readline()
        assert "http://127.0.0.1:" in line and "300 gaussians" in line, (line, proc.stderr.read())
        url = line.split(" at ")[1].split()[0]
        with urllib.request.urlopen(url, timeout=30) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert "Traceback" not in err, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# ----------------------------------------------------------------------------------- a map
def test_a_map_shows_its_valid_cells_coloured_by_their_pixels(tiny: dict, tmp_path: Path) -> None:
    from acesplat.core.scene import read_split
    from acesplat.scr.localize import Localizer
    from acesplat.scr.map_view import map_view
    from acesplat.scr.mapfile import encoder_for_map, load_map
    from acesplat.splatcore.validity import cell_pixels, cell_validity

    view = map_view(tiny["map"])
    split = read_split(tiny["scene"], "train")
    assert [c.name for c in view.cameras] == [f.name for f in split.frames]
    for c, f in zip(view.cameras, split.frames):
        np.testing.assert_array_equal(c.c2w, f.pose)
    m = load_map(tiny["map"])
    loc = Localizer(m.network(encoder_for_map(m, tiny["map"])), m.short_side)
    f = split.frames[0]
    rgb = f.load_rgb()
    coords, intr = loc.predict(rgb, f.intrinsics)
    valid = cell_validity(coords, f.pose, intr).valid
    n0 = int(valid.sum())
    assert n0 > 0.5 * valid.size
    np.testing.assert_allclose(view.points.points[:n0], coords[valid], atol=1e-6)
    u, v = cell_pixels(*valid.shape)[valid].astype(int).T
    small = cv2.resize(rgb, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(view.points.colors[:n0], small[v, u])
    assert 0 < view.points.point_size < 1.0
    capped = map_view(tiny["map"], max_points=100)
    assert len(capped.points.points) == 100 and "100 of" in capped.note
    if chromium() is not None:
        server, _ = serve(view, "127.0.0.1", 0)
        try:
            im = capture_until(f"http://127.0.0.1:{server.get_port()}", settled(lambda im: drawn(im) > 0.3))
        finally:
            server.stop()
        cv2.imwrite(str(tmp_path / "map.png"), im)
        assert drawn(im) > 0.3 and canvas(im).std() > 20, f"the map's canvas looks blank: {tmp_path}"


def test_a_splat_folder_shows_the_cameras_of_its_recorded_scene(tiny: dict, tmp_path: Path) -> None:
    from acesplat.apps.view_cmd import load_view_scene

    folder = tmp_path / "splat"
    folder.mkdir()
    write_ply(folder / "gaussians.ply", red_cube(100))
    manifest = {"format": "acesplat-splat", "version": 1, "short_side": 64, "background": [0, 0, 0]}
    (folder / "splat.json").write_text(json.dumps({**manifest, "scene": str(tiny["scene"])}))
    view = load_view_scene(folder, None, None, 1000)
    assert len(view.splats.centers) == 100 and len(view.cameras) == 12 and view.note == ""
    (folder / "splat.json").write_text(json.dumps({**manifest, "scene": str(tmp_path / "gone")}))
    view = load_view_scene(folder, None, None, 1000)
    assert view.cameras == [] and "not there" in view.note
    (folder / "splat.json").unlink()  # a bare folder of Gaussians: shown without cameras
    view = load_view_scene(folder, None, None, 1000)
    assert len(view.splats.centers) == 100 and view.cameras == []
    assert len(load_view_scene(folder, tiny["scene"], None, 1000).cameras) == 12


# ----------------------------------------------------------------------------------- bad input
def one_line_error(args: list[str], *needles: str) -> None:
    res = runner.invoke(app, ["view", *args])
    assert res.exit_code == 2, res.output
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("error: "), res.stderr
    for n in needles:
        assert n in res.stderr, res.stderr


def test_view_kind_reads_layout_and_magic(tmp_path: Path) -> None:
    write_ply(tmp_path / "g.ply", red_cube(3))
    assert view_kind(tmp_path / "g.ply") == "ply"
    (tmp_path / "s").mkdir()
    write_ply(tmp_path / "s" / "gaussians.ply", red_cube(3))
    assert view_kind(tmp_path / "s") == "splat"
    (tmp_path / "m.pt").write_bytes(b"PK\x03\x04rest")
    assert view_kind(tmp_path / "m.pt") == "map"
    with pytest.raises(InputError, match="neither a splat"):
        view_kind(tmp_path)


def test_bad_inputs_are_one_line_and_exit_2(tmp_path: Path) -> None:
    one_line_error([str(tmp_path / "nope.ply")], "nope.ply", "not found")
    (tmp_path / "notes.txt").write_text("hello\n")
    one_line_error([str(tmp_path / "notes.txt")], "notes.txt", "neither a splat")
    (tmp_path / "empty").mkdir()
    one_line_error([str(tmp_path / "empty")], "empty", "without gaussians.ply")
    (tmp_path / "fake.pt").write_bytes(b"PK\x03\x04 not a torch archive")
    one_line_error([str(tmp_path / "fake.pt")], "fake.pt", "not a loadable map")
    write_ply(tmp_path / "g.ply", red_cube(3))
    one_line_error([str(tmp_path / "g.ply"), "--max-points", "0"], "--max-points")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        one_line_error([str(tmp_path / "g.ply"), "--port", str(port)], f"127.0.0.1:{port}", "--port")
