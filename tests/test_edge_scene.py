"""A tiny analytic scene and a tiny map for the export and edge tests (the fixtures are in tests/conftest.py).

The room is a box whose six faces carry distinctive random textures; frames are ray cast exactly,
so the true pose of every image is known. Once the built-in generator (acesplat.synth) offers
``synthesize`` this module can delegate to it; the analytic room keeps the tests independent of it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import look_at
from acesplat.core.scene import write_frame

ROOM = np.array([4.0, 3.0, 2.5])
TEX = 256
TEXTURE_BLUR = 1.5
"""Gaussian blur of each texture (texels): a texel is about half a pixel in the tiny views, so unblurred
textures alias and a view moved by a centimetre looks like another image."""


def _texture(rng: np.random.Generator) -> np.ndarray:
    """Multi-scale colour noise plus random shapes: every patch looks different."""
    img = np.zeros((TEX, TEX, 3), np.float32)
    for cell, amp in ((64, 0.5), (16, 0.3), (4, 0.2)):
        small = rng.random((TEX // cell + 1, TEX // cell + 1, 3)).astype(np.float32)
        img += amp * cv2.resize(small, (TEX, TEX), interpolation=cv2.INTER_CUBIC)
    img = np.clip(img * 255, 0, 255).astype(np.uint8)
    for _ in range(40):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        p = tuple(int(v) for v in rng.integers(0, TEX, 2))
        if rng.random() < 0.5:
            cv2.circle(img, p, int(rng.integers(4, 20)), c, -1)
        else:
            q = tuple(int(v) for v in np.array(p) + rng.integers(-24, 24, 2))
            cv2.rectangle(img, p, q, c, -1)
    return cv2.GaussianBlur(img, (0, 0), TEXTURE_BLUR)


def render(textures: list[np.ndarray], T_c2w: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast RGB (H, W, 3) uint8 and z-depth (H, W) of the textured box seen from ``T_c2w``."""
    ys, xs = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    d_cam = np.stack([(xs - intr.cx) / intr.fx, (ys - intr.cy) / intr.fy, np.ones_like(xs)], -1)
    R, o = T_c2w[:3, :3], T_c2w[:3, 3]
    d = d_cam @ R.T
    best_t = np.full(xs.shape, np.inf)
    face = np.zeros(xs.shape, int)
    for axis in range(3):
        for side, bound in ((0, 0.0), (1, ROOM[axis])):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (bound - o[axis]) / d[..., axis]
            ok = (t > 1e-6) & (t < best_t)
            best_t = np.where(ok, t, best_t)
            face = np.where(ok, 2 * axis + side, face)
    X = o + d * best_t[..., None]
    rgb = np.zeros(xs.shape + (3,), np.uint8)
    for f in range(6):
        axis = f // 2
        u_ax, v_ax = [a for a in range(3) if a != axis]
        m = face == f
        u = (X[..., u_ax] / ROOM[u_ax] * (TEX - 1)).astype(np.float32)
        v = (X[..., v_ax] / ROOM[v_ax] * (TEX - 1)).astype(np.float32)
        sample = cv2.remap(textures[f], u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        rgb[m] = sample[m]
    depth = best_t * d_cam[..., 2]
    return rgb, depth.astype(np.float32)


def camera_poses(n: int, phase: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Cameras near the room's centre turning around, looking at the walls."""
    poses = []
    for i in range(n):
        yaw = phase + 2 * np.pi * i / n
        eye = ROOM / 2 + np.array([0.3 * np.cos(3 * yaw), 0.3 * np.sin(2 * yaw), 0.1 * np.sin(yaw)])
        eye = eye + rng.normal(0, 0.03, 3)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), -0.15 + 0.1 * np.sin(2 * yaw)])
        poses.append(look_at(eye, target))
    return poses


def jitter(T: np.ndarray, rng: np.random.Generator, metres: float, degrees: float) -> np.ndarray:
    """``T`` moved by ``metres`` and turned by ``degrees`` about a random axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rvec = np.radians(degrees) * axis
    R, _ = cv2.Rodrigues(rvec)
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ R
    d = rng.normal(size=3)
    out[:3, 3] += metres * d / np.linalg.norm(d)
    return out


def make_room_scene(
    out: Path,
    train: int = 24,
    test: int = 6,
    size: tuple[int, int] = (64, 80),
    seed: int = 0,
    test_offset_m: float = 0.02,
    test_offset_deg: float = 1.0,
) -> Path:
    """Write a textured-box scene in the ACE layout (train/ and test/) and return its folder.

    Test views are training views moved by a few centimetres and turned by a degree: close enough
    for a map trained in seconds to recognise them, far enough that a copied pose would be wrong.
    """
    rng = np.random.default_rng(seed)
    textures = [_texture(rng) for _ in range(6)]
    h, w = size
    intr = Intrinsics.from_focal(0.9 * w, w, h)
    train_poses = camera_poses(train, 0.0, rng)
    picks = np.linspace(0, train - 1, test).round().astype(int)
    test_poses = [jitter(train_poses[i], rng, test_offset_m, test_offset_deg) for i in picks]
    for split, poses in (("train", train_poses), ("test", test_poses)):
        for i, T in enumerate(poses):
            rgb, depth = render(textures, T, intr)
            write_frame(out / split, f"{i:04d}", rgb, T, intr.K, depth=depth)
    return out


# ----------------------------------------------------------------------------------- tiny map + bundle
ENCODER = dict(c1=8, c2=16, c3=32, c4=32, res2=32, out=32)


def cell_targets(frame) -> np.ndarray:
    """True scene coordinates (h, w, 3) of a frame's stride-8 cells, from its depth map."""
    from acesplat.core.geometry import transform_points
    from acesplat.core.grid import cell_centers

    d = frame.load_depth()
    h, w = d.shape[0] // 8, d.shape[1] // 8
    c = cell_centers(h, w)
    z = d[c[:, 1].astype(int), c[:, 0].astype(int)]
    return transform_points(frame.pose, frame.intrinsics.unproject(c, z)).reshape(h, w, 3)


def augmented_view(
    frame, gray: np.ndarray, depth: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A randomly rotated, scaled and shifted copy of a training image with its cells' true coordinates.

    Returns the warped image (H, W) float32, the stride-8 cell coordinates (h, w, 3) and their validity
    (h, w) (a cell whose source pixel left the image has no target). The warp is a similarity about the
    image centre (rotation AUG_DEG, scale AUG_SCALE, shift AUG_PX); each cell's target is the training
    image's depth, read at the cell's source pixel and unprojected there, so no other view is used.
    """
    from acesplat.core.geometry import transform_points
    from acesplat.core.grid import cell_centers

    H, W = gray.shape
    a = np.radians(rng.uniform(-AUG_DEG, AUG_DEG))
    k = rng.uniform(1 / AUG_SCALE, AUG_SCALE)
    t = rng.uniform(-AUG_PX, AUG_PX, 2)
    centre = np.array([W / 2.0, H / 2.0])
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) / k  # output pixel -> source pixel
    inv = np.concatenate([R, (centre - R @ (centre + t))[:, None]], axis=1)
    img = cv2.warpAffine(
        gray, inv, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
    )
    h, w = H // 8, W // 8
    src = cell_centers(h, w) @ inv[:, :2].T + inv[:, 2]
    ok = (src[:, 0] >= 0) & (src[:, 0] <= W - 1) & (src[:, 1] >= 0) & (src[:, 1] <= H - 1)
    z = cv2.remap(depth, *(v.astype(np.float32).reshape(1, -1) for v in src.T), cv2.INTER_LINEAR).reshape(-1)
    X = transform_points(frame.pose, frame.intrinsics.unproject(src, z.astype(np.float64)))
    return img, X.reshape(h, w, 3), ok.reshape(h, w)


AUG_DEG, AUG_SCALE, AUG_PX = 3.0, 1.04, 3.0
"""Augmentation range of the tiny map: about the test views' offsets (a few degrees, a few pixels)."""


def train_tiny_map(scene: Path, out_dir: Path, steps: int = 600, seed: int = 0, lr: float = 5e-3) -> tuple[Path, Path]:
    """A map that localizes the tiny room within a minute: encoder and head fitted to depth-derived coordinates.

    ACE's reprojection recipe with a random encoder needs minutes to localize anything; the export
    and edge tests need a map that does localize, so this one is fitted directly (L1 on true
    coordinates, full batch, cosine-decayed Adam) on randomly rotated, scaled and shifted copies of the
    training images, so that it recognises views off the training trajectory. The result is an ordinary
    map file plus an ordinary encoder file, saved and loaded by the project's own code.
    """
    import torch

    from acesplat.core.scene import read_split
    from acesplat.scr.encoders import EncoderIdentity, file_sha256
    from acesplat.scr.mapfile import SceneMap, save_map
    from acesplat.scr.network import Encoder, EncoderConfig, Head, HeadConfig, SCRNetwork

    split = read_split(scene, "train")
    gray = np.stack([cv2.cvtColor(f.load_rgb(), cv2.COLOR_RGB2GRAY) for f in split.frames]).astype(np.float32)
    depths = [f.load_depth() for f in split.frames]
    rng = np.random.default_rng(seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny convolutions: one thread is faster, and immune to a busy machine
    try:
        torch.manual_seed(seed)
        enc = Encoder(EncoderConfig(**ENCODER))
        mean = torch.from_numpy(np.mean([f.pose[:3, 3] for f in split.frames], axis=0)).float()
        head = Head(mean, in_channels=enc.cfg.out, cfg=HeadConfig(width=64, blocks=1))
        net = SCRNetwork(enc, head)
        opt = torch.optim.Adam(net.parameters(), lr=lr)
        for it in range(steps):
            views = [augmented_view(f, g, d, rng) for f, g, d in zip(split.frames, gray, depths)]
            x = torch.from_numpy(np.stack([v[0] for v in views]))[:, None]
            y = torch.from_numpy(np.stack([v[1] for v in views])).float().permute(0, 3, 1, 2)
            ok = torch.from_numpy(np.stack([v[2] for v in views]))
            for g in opt.param_groups:
                g["lr"] = lr * 0.5 * (1 + np.cos(np.pi * it / steps))
            loss = (net(x) - y).abs().sum(1)[ok].mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    finally:
        torch.set_num_threads(threads)
    net.eval()
    enc_path = out_dir / "encoder_tiny.pt"
    torch.save(enc.state_dict(), enc_path)
    ident = EncoderIdentity(enc_path.name, file_sha256(enc_path), str(enc_path.resolve()))
    map_path = out_dir / "tiny.map"
    save_map(
        map_path,
        SceneMap(
            head.eval(),
            ident,
            mean.numpy().astype(np.float64),
            short_side=int(gray.shape[1]),
            metadata={"scene": str(scene.resolve())},
        ),
    )
    return map_path, enc_path


TINY_OFFSET_M, TINY_OFFSET_DEG = 0.03, 2.0
"""How far the tiny scene's test views are moved and turned from the training views they start from."""


def tiny_setup(root: Path) -> dict:
    """Scene, map, encoder and an exported FP32+INT8 bundle in ``root`` (tests/conftest.py builds it once)."""
    from export.bundle_export import ExportOptions, export_bundle

    scene = make_room_scene(
        root / "room", train=12, test=4, test_offset_m=TINY_OFFSET_M, test_offset_deg=TINY_OFFSET_DEG
    )
    map_path, enc_path = train_tiny_map(scene, root)
    rep = export_bundle(map_path, root / "bundle", ExportOptions(int8=True))
    return {
        "root": root,
        "scene": scene,
        "map": map_path,
        "encoder": enc_path,
        "bundle": root / "bundle",
        "manifest": rep.manifest,
    }


# ----------------------------------------------------------------------------------- the scene itself
def test_rendered_depth_and_pose_agree(tmp_path: Path) -> None:
    """Cells unprojected with the rendered depth and the recorded pose land on the room's walls."""
    from acesplat.core.scene import read_split

    scene = make_room_scene(tmp_path / "room", train=2, test=1)
    for f in read_split(scene, "train").frames:
        X = cell_targets(f).reshape(-1, 3)
        on_wall = np.min(np.abs(np.concatenate([X, ROOM - X], axis=1)), axis=1)
        assert np.all(on_wall < 1e-3)
