"""The `acesplat view` scene: Gaussians or an SCR point cloud plus the mapping cameras, served as a viser page.

Everything here works on plain arrays (torch-free); the map's point cloud is computed on the training floor
(acesplat.scr.map_view) and handed over as a :class:`ViewScene`. viser is imported only when a page is served.

Our poses are 4x4 camera-to-world with OpenCV camera axes; viser's camera frustums use the same camera axes and a
scene node's (wxyz, position) is its parent-from-local transform, so a pose becomes a node by
:func:`viser_pose` alone (rotation to a wxyz quaternion, translation as is).
"""

from __future__ import annotations

import contextlib
import io
import math
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.errors import InputError
from acesplat.core.gaussians import Gaussians, sh_dc_to_rgb
from acesplat.core.geometry import matrix_to_quat, quat_to_matrix, rigidity_problem
from acesplat.core.scene import SceneSplit


@dataclass(frozen=True)
class ViewConfig:
    """Where the viewer listens and how much it sends to the browser."""

    host: str = knob("127.0.0.1", "Address the viewer listens on (0.0.0.0: every interface of this machine).")
    port: int = knob(8080, "Port of the viewer's page and websocket (0: any free port).")
    max_points: int = knob(
        500_000, "Most Gaussians or map points sent to the browser (evenly subsampled above it), so it stays smooth."
    )

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise InputError(None, f"--port must be in 0..65535, got {self.port}")
        if self.max_points < 1:
            raise InputError(None, f"--max-points must be positive, got {self.max_points}")
        if not self.host:
            raise InputError(None, "--host must not be empty")


THUMBNAIL_SHORT_SIDE = 48
"""Short side in pixels of a mapping image drawn inside its frustum."""
FRUSTUM_FRACTION = 0.04
"""A frustum's depth as a fraction of the content's extent."""


@dataclass
class ViewCamera:
    """One mapping camera: camera-to-world ``c2w`` (4, 4), its intrinsics, optional thumbnail RGB uint8 (h, w, 3)."""

    c2w: np.ndarray
    intrinsics: Intrinsics
    name: str = ""
    image: np.ndarray | None = None

    def __post_init__(self) -> None:
        problem = rigidity_problem(self.c2w)
        if problem:
            raise ValueError(f"camera {self.name!r}: {problem}")

    @property
    def fov_y(self) -> float:
        """Vertical field of view, radians."""
        return 2.0 * math.atan(self.intrinsics.height / (2.0 * self.intrinsics.fy))

    @property
    def aspect(self) -> float:
        """Width over height."""
        return self.intrinsics.width / self.intrinsics.height


@dataclass
class SplatLayer:
    """Gaussians as viser draws them: centres (N, 3), covariances (N, 3, 3), colours (N, 3) in [0, 1], opacities
    (N, 1) in (0, 1); all float32."""

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray


@dataclass
class PointLayer:
    """Points (N, 3) float32 with colours (N, 3) uint8, drawn ``point_size`` scene units wide."""

    points: np.ndarray
    colors: np.ndarray
    point_size: float


@dataclass
class ViewScene:
    """What one viewer page shows: Gaussians and/or a point cloud, and the mapping cameras."""

    title: str
    splats: SplatLayer | None = None
    points: PointLayer | None = None
    cameras: list[ViewCamera] = field(default_factory=list)
    note: str = ""
    """One line on what was left out (e.g. subsampling), printed beside the URL."""

    def content(self) -> np.ndarray:
        """The drawn positions (N, 3): Gaussian centres and points."""
        parts = [self.splats.centers] if self.splats is not None else []
        parts += [self.points.points] if self.points is not None else []
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)


def subsample_index(n: int, max_n: int) -> np.ndarray:
    """Indices of at most ``max_n`` of ``n`` items, evenly spaced and increasing (all of them when n <= max_n)."""
    if max_n < 1:
        raise ValueError(f"max_n must be positive, got {max_n}")
    if n <= max_n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_n).round().astype(np.int64))


def splat_layer(g: Gaussians, max_points: int) -> SplatLayer:
    """Gaussians in 3DGS's pre-activation parameters to viser's: covariance R diag(s^2) R^T from the unit
    quaternion and the scales, colour from the SH DC term (clipped to [0, 1]), sigmoid opacity."""
    g = g.subset(subsample_index(len(g), max_points))
    R = quat_to_matrix(g.unit_quats())
    s2 = np.exp(2.0 * g.log_scales.astype(np.float64))
    cov = np.einsum("nij,nj,nkj->nik", R, s2, R)
    return SplatLayer(
        centers=np.ascontiguousarray(g.means, np.float32),
        covariances=cov.astype(np.float32),
        rgbs=np.clip(sh_dc_to_rgb(g.sh[:, 0, :]), 0.0, 1.0).astype(np.float32),
        opacities=g.opacities().astype(np.float32)[:, None],
    )


def point_layer(points: np.ndarray, colors: np.ndarray, point_size: float, max_points: int) -> PointLayer:
    """A point cloud (N, 3) with colours (N, 3) uint8, evenly subsampled to ``max_points``."""
    points, colors = np.asarray(points), np.asarray(colors)
    if points.ndim != 2 or points.shape[1] != 3 or colors.shape != points.shape:
        raise ValueError(f"points and colors must both be (N, 3), got {points.shape} and {colors.shape}")
    if colors.dtype != np.uint8:
        raise TypeError(f"colors must be uint8, got {colors.dtype}")
    if not point_size > 0:
        raise ValueError(f"point_size must be positive, got {point_size}")
    idx = subsample_index(len(points), max_points)
    return PointLayer(np.ascontiguousarray(points[idx], np.float32), np.ascontiguousarray(colors[idx]), point_size)


def thumbnail(rgb: np.ndarray) -> np.ndarray:
    """An RGB image (H, W, 3) uint8 shrunk to a short side of THUMBNAIL_SHORT_SIDE for its frustum."""
    import cv2

    h, w = rgb.shape[:2]
    s = THUMBNAIL_SHORT_SIDE / min(h, w)
    if s >= 1:
        return rgb
    return cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


def split_cameras(split: SceneSplit) -> list[ViewCamera]:
    """The cameras of a scene split (the mapping images of its training split), each with its thumbnail."""
    return [ViewCamera(f.pose, f.intrinsics, f.name, thumbnail(f.load_rgb())) for f in split.frames]


def splat_view(g: Gaussians, title: str, split: SceneSplit | None, max_points: int) -> ViewScene:
    """The Gaussians ``g`` (subsampled evenly to ``max_points``) and, when given, the cameras of ``split``."""
    layer = splat_layer(g, max_points)
    note = f"{len(layer.centers)} of {len(g)} Gaussians shown (--max-points)" if len(layer.centers) < len(g) else ""
    cameras = split_cameras(split) if split is not None else []
    return ViewScene(title=title, splats=layer, cameras=cameras, note=note)


def viser_pose(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz (4,), position (3,)) of a viser node placed at camera-to-world ``c2w`` (4, 4), OpenCV axes."""
    problem = rigidity_problem(c2w)
    if problem:
        raise ValueError(problem)
    return matrix_to_quat(c2w[:3, :3]), np.asarray(c2w[:3, 3], np.float64).copy()


def scene_up(cameras: list[ViewCamera]) -> np.ndarray | None:
    """The world's up direction (3,) as the cameras hold it (the mean of their -y axes), or None when they do
    not agree on one (no cameras, or rolled every way)."""
    if not cameras:
        return None
    up = -np.mean([c.c2w[:3, 1] for c in cameras], axis=0)
    n = np.linalg.norm(up)
    return up / n if n > 0.5 else None


def robust_box(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (3,) and diagonal of the 2nd-98th percentile box of ``points`` (N, 3) (stray points ignored)."""
    if len(points) == 0:
        return np.zeros(3), 1.0
    lo, hi = np.percentile(points, [2, 98], axis=0)
    return (lo + hi) / 2.0, max(float(np.linalg.norm(hi - lo)), 1e-3)


@dataclass(frozen=True)
class InitialView:
    """Where the page's camera starts (world coordinates) and its vertical field of view (radians)."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray | None
    fov_y: float


def initial_view(scene: ViewScene) -> InitialView:
    """The middle mapping camera's view (the scene as its images show it); without cameras, an outside view of the
    content's box."""
    centre, diag = robust_box(scene.content())
    up = scene_up(scene.cameras)
    if scene.cameras:
        cam = scene.cameras[len(scene.cameras) // 2]
        eye = cam.c2w[:3, 3]
        forward = cam.c2w[:3, 2]
        depth = float(np.dot(centre - eye, forward))
        look = eye + forward * (depth if depth > 1e-3 else 0.25 * diag)
        return InitialView(eye.copy(), look, up, cam.fov_y)
    direction = np.array([1.0, 1.0, 1.0]) / math.sqrt(3.0)
    return InitialView(centre + 1.5 * diag * direction, centre, up, math.radians(50.0))


def build_scene(server: Any, scene: ViewScene) -> dict[str, int]:
    """Add ``scene`` to a viser server (``viser.ViserServer``); returns the counts drawn
    (``gaussians``, ``points``, ``cameras``)."""
    api = server.scene
    up = scene_up(scene.cameras)
    if up is not None:
        api.set_up_direction(up)
    if scene.splats is not None:
        s = scene.splats
        api.add_gaussian_splats("/gaussians", s.centers, s.covariances, s.rgbs, s.opacities)
    if scene.points is not None:
        p = scene.points
        api.add_point_cloud("/points", p.points, p.colors, point_size=p.point_size, point_shape="rounded")
    _, diag = robust_box(scene.content())
    for i, cam in enumerate(scene.cameras):
        wxyz, position = viser_pose(cam.c2w)
        api.add_camera_frustum(
            f"/cameras/{i:05d}",
            fov=cam.fov_y,
            aspect=cam.aspect,
            scale=FRUSTUM_FRACTION * diag,
            thickness=0.1 * FRUSTUM_FRACTION * diag,
            color=(255, 140, 0),
            image=cam.image,
            wxyz=wxyz,
            position=position,
        )
    view = initial_view(scene)
    cam0 = server.initial_camera
    cam0.position = tuple(float(v) for v in view.position)
    cam0.look_at = tuple(float(v) for v in view.look_at)
    if view.up is not None:
        cam0.up = tuple(float(v) for v in view.up)
    cam0.fov = float(view.fov_y)
    return {
        "gaussians": 0 if scene.splats is None else len(scene.splats.centers),
        "points": 0 if scene.points is None else len(scene.points.points),
        "cameras": len(scene.cameras),
    }


def check_port_free(host: str, port: int) -> None:
    """InputError when ``host`` does not resolve or ``port`` is taken there (viser would move to the next port
    without a word, or wait forever when none binds)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as e:
        raise InputError(None, f"--host {host!r} does not resolve ({e.strerror or e})") from None
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(addr)
            except OSError as e:
                raise InputError(None, f"cannot listen on {host}:{port} ({e.strerror or e}); pass --port") from None


def serve(scene: ViewScene, host: str, port: int) -> tuple[Any, dict[str, int]]:
    """Start a viser server on ``host``:``port`` (0: any free port) showing ``scene``; returns the running server
    (stop it with ``server.stop()``) and the counts drawn. It serves from its own thread."""
    import viser

    check_port_free(host, port)
    with contextlib.redirect_stdout(io.StringIO()):  # viser prints its own banner; the command prints one line
        server = viser.ViserServer(host=host, port=port, label=scene.title, verbose=False)
    if port and server.get_port() != port:  # taken between the check and viser's bind: viser moved on
        server.stop()
        raise InputError(None, f"cannot listen on {host}:{port} (in use); pass --port")
    try:
        counts = build_scene(server, scene)
    except BaseException:
        server.stop()
        raise
    return server, counts


def page_url(host: str, port: int) -> str:
    """The address to open in a browser (a wildcard host is reached through localhost)."""
    shown = "localhost" if host in ("0.0.0.0", "::", "") else (f"[{host}]" if ":" in host else host)
    return f"http://{shown}:{port}"


PLY_MAGIC = b"ply\n"
TORCH_ZIP_MAGIC = b"PK\x03\x04"
"""torch.save writes a zip archive: how a map file starts."""
SPLAT_PLY = "gaussians.ply"
"""The Gaussians of a splat folder (acesplat.splat.splatfile)."""


def view_kind(path: str | Path) -> str:
    """What ``path`` holds, from its layout and first bytes: "splat" (a folder from `acesplat splat`), "ply" (a
    3DGS .ply) or "map" (a map file from `acesplat map`); InputError naming the file otherwise."""
    path = Path(path)
    neither = "neither a splat (a folder from `acesplat splat` or a 3DGS .ply) nor a map (from `acesplat map`)"
    if not path.exists():
        raise InputError(path, "not found")
    if path.is_dir():
        if (path / SPLAT_PLY).is_file():
            return "splat"
        raise InputError(path, f"{neither}: a folder without {SPLAT_PLY}")
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as e:
        raise InputError(path, f"cannot read ({e.strerror or e})") from None
    if head == PLY_MAGIC:
        return "ply"
    if head == TORCH_ZIP_MAGIC:
        return "map"
    raise InputError(path, neither)
