"""What `acesplat view` shows of a map: its SCR point cloud over the mapping images, coloured by their pixels.

Each training image goes through the map's network at the map's resolution (the path `acesplat eval` takes); a
cell's coordinate is kept when it passes the splat seeding's validity test (in front of the camera, reprojecting
onto its own cell with the image's pose: acesplat.splatcore.validity) and takes the colour of its cell's pixel.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from acesplat.core.config import knob_default
from acesplat.core.errors import InputError
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.core.scene import TRAIN, read_split
from acesplat.core.viewer import ViewCamera, ViewConfig, ViewScene, point_layer, thumbnail
from acesplat.scr.localize import Localizer
from acesplat.scr.mapfile import encoder_for_map, load_map
from acesplat.splatcore.validity import ValidityConfig, cell_pixels, cell_validity


def map_scene_path(map_path: str | Path, metadata: dict, scene: str | Path | None) -> Path:
    """The scene whose training images a map was made from: ``scene`` if given, else the one the map records."""
    if scene is not None:
        return Path(scene)
    recorded = metadata.get("scene")
    if not recorded:
        raise InputError(map_path, "the map records no scene; pass --scene")
    return Path(recorded)


def map_view(
    map_path: str | Path,
    scene: str | Path | None = None,
    encoder: str | Path | None = None,
    max_points: int = knob_default(ViewConfig, "max_points"),
    progress: Callable[[int, int], None] | None = None,
) -> ViewScene:
    """The SCR point cloud of the map at ``map_path`` over its scene's training split, and the mapping cameras.

    Points (N, 3) are the valid cells' coordinates; colours the RGB of each cell's centre pixel at the network's
    input size; the point size is the median width a cell covers on its surface (8 px at the cell's depth).
    """
    m = load_map(map_path)
    enc = encoder_for_map(m, map_path, encoder)
    split = read_split(map_scene_path(map_path, m.metadata, scene), TRAIN)
    localizer = Localizer(m.network(enc), m.short_side)
    cfg = ValidityConfig()
    points, colors, widths, cameras = [], [], [], []
    for i, frame in enumerate(split.frames):
        rgb = frame.load_rgb()
        coords, intr = localizer.predict(rgb, frame.intrinsics)
        valid = cell_validity(coords, frame.pose, intr, cfg)
        h, w = coords.shape[:2]
        small = cv2.resize(rgb, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
        uv = cell_pixels(h, w)[valid.valid]
        u = np.clip(uv[:, 0].astype(np.int64), 0, intr.width - 1)
        v = np.clip(uv[:, 1].astype(np.int64), 0, intr.height - 1)
        points.append(coords[valid.valid].astype(np.float32))
        colors.append(small[v, u])
        widths.append(OUTPUT_STRIDE * valid.depth[valid.valid] / intr.fx)
        cameras.append(ViewCamera(frame.pose, frame.intrinsics, frame.name, thumbnail(rgb)))
        if progress:
            progress(i + 1, len(split.frames))
    pts = np.concatenate(points)
    if len(pts) == 0:
        raise InputError(map_path, f"no SCR coordinate of the map passes the validity test on {split.root}/{TRAIN}")
    width = float(np.median(np.concatenate(widths)))
    layer = point_layer(pts, np.concatenate(colors), width, max_points)
    note = f"{len(layer.points)} of {len(pts)} points shown (--max-points)" if len(layer.points) < len(pts) else ""
    return ViewScene(title=f"map {Path(map_path).name}", points=layer, cameras=cameras, note=note)
