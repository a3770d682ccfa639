"""Importers that write the ACE scene layout from other formats (torch-free).

- ``import_transforms_json``: instant-ngp / nerfstudio / Blender-NeRF ``transforms.json`` (OpenGL axes).
- ``import_colmap_text``: COLMAP text model (``cameras.txt``, ``images.txt``; world-to-camera).
- ``import_scene``: either, chosen by ``detect_format``.
- ``sfm.pose_images``: images without poses, posed with pycolmap (``acesplat pose``).

Conventions on import (see ``common``): OpenCV camera axes and pixel centres; natural-name order;
every 8th frame to test unless the source ships a split.
"""

from acesplat.importers.colmap_text import import_colmap_text
from acesplat.importers.common import ImportConfig, ImportSummary
from acesplat.importers.dispatch import detect_format, import_scene
from acesplat.importers.transforms_json import import_transforms_json

__all__ = [
    "ImportConfig",
    "ImportSummary",
    "detect_format",
    "import_colmap_text",
    "import_scene",
    "import_transforms_json",
]
