"""The bundle: a directory of models plus a manifest that says what they are and proves they are intact.

Torch-free so the edge runtime can open and verify a bundle. The file list is generic (role, path,
sha256, size) so later stages can add their models without a format change; the ``scr`` section
describes the scene coordinate regression models that exist today.

Loading checks every listed file's size and sha256 before anything uses it: a truncated or
modified model must give a clear error, never a wrong pose.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from acesplat.core.atomic import write_json
from acesplat.core.errors import InputError
from acesplat.core.grid import DENSE_OUTPUT_STRIDE, OUTPUT_STRIDE

BUNDLE_FORMAT = "acesplat-bundle"
BUNDLE_VERSION = 2
"""1: the SCR graphs output coordinates only; a splat initializer (if any) takes the image and runs its own encoder.
2: the SCR graphs (FP32 and INT8) also output the encoder's features, and the initializer takes those features.
Version 1 bundles still load: localization reads the coordinates output of either; refinement seeds from SCR
coordinates when the initializer is a version 1 graph."""
MANIFEST_NAME = "manifest.json"

SCR_COORDS_OUTPUT = "coords"
SCR_FEATURES_OUTPUT = "features"
"""Output names of the SCR graphs: coordinates (1, 3, H/8, W/8) and, from version 2, the encoder's features
(1, C, H/8, W/8) that the splat initializer takes, so refinement reuses what localization computed."""

ROLE_SCR_FP32 = "scr_fp32"
ROLE_SCR_INT8 = "scr_int8"
ROLE_SCR_INT8_VNNI = "scr_int8_vnni"
"""The INT8 twin in U8S8: about twice as fast where the CPU multiplies uint8 by int8 without saturating (VNNI, AMX);
the device's check runs it only where it matches FP32 as closely as the default INT8 graph (edge.int8_check)."""
ROLE_KEYFRAMES = "keyframes"
"""Mapping images with their poses and depth (acesplat.align.keyframe_set), for pose refinement."""
ROLE_INT8_CHECK = "int8_check"
"""A few prepared frames with their FP32 coordinates (acesplat.core.check_frames), for the device's INT8 check."""
PRECISION_ROLES = {"fp32": ROLE_SCR_FP32, "int8": ROLE_SCR_INT8, "int8_vnni": ROLE_SCR_INT8_VNNI}
INT8_PRECISIONS = ("int8", "int8_vnni")
"""The INT8 graphs a bundle can carry, the default first: `--int8` runs the fastest one the device's check passes."""


def sha256_of(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class BundleFile:
    """One file of a bundle; ``path`` is relative to the bundle directory, POSIX separators."""

    role: str
    path: str
    sha256: str
    bytes: int

    def as_dict(self) -> dict[str, Any]:
        return {"role": self.role, "path": self.path, "sha256": self.sha256, "bytes": self.bytes}


def describe_file(root: str | Path, rel_path: str, role: str) -> BundleFile:
    """The manifest entry of a file already written inside the bundle directory ``root``."""
    p = Path(root) / rel_path
    return BundleFile(role=role, path=PurePosixPath(rel_path).as_posix(), sha256=sha256_of(p), bytes=p.stat().st_size)


@dataclass
class Bundle:
    """A verified bundle: its directory, the parsed manifest and its files by role."""

    root: Path
    manifest: dict[str, Any]
    files: dict[str, BundleFile] = field(default_factory=dict)

    def path(self, role: str) -> Path:
        if role not in self.files:
            raise InputError(self.root / MANIFEST_NAME, f"bundle has no '{role}' file (has: {', '.join(self.files)})")
        return self.root / self.files[role].path

    def has(self, role: str) -> bool:
        return role in self.files

    @property
    def scene_name(self) -> str:
        return str(self.manifest.get("scene", {}).get("name", ""))

    @property
    def scene_path(self) -> str | None:
        return self.manifest.get("scene", {}).get("path")

    @property
    def format_version(self) -> int:
        return int(self.manifest.get("format_version", 1))

    @property
    def scr(self) -> dict[str, Any]:
        return self.manifest["scr"]

    @property
    def encoder_rank(self) -> int | None:
        """The rank of the SCR graph's low-rank encoder layer (`acesplat export --encoder-rank`); None: exact."""
        lowrank = self.scr.get("encoder_lowrank")
        return int(lowrank["rank"]) if isinstance(lowrank, dict) and "rank" in lowrank else None

    @property
    def input_size(self) -> tuple[int, int]:
        """(H, W) of the grayscale image the SCR models take."""
        h, w = self.scr["input_size"]
        return int(h), int(w)

    @property
    def dynamic_size(self) -> bool:
        """Whether the SCR graphs also take other multiples of 8 than ``input_size`` (bundles since the dynamic
        graph; ``input_size`` is still the size the export checked)."""
        return bool(self.scr.get("dynamic_size", False))

    @property
    def output_stride(self) -> int:
        return int(self.scr["output_stride"])

    def scr_model(self, precision: str) -> Path:
        """Path of the SCR model for 'fp32', 'int8' or 'int8_vnni'."""
        if precision not in PRECISION_ROLES:
            raise InputError(None, f"precision must be one of {sorted(PRECISION_ROLES)}, got {precision!r}")
        role = PRECISION_ROLES[precision]
        if role not in self.files:
            raise InputError(
                self.root / MANIFEST_NAME,
                f"bundle has no {precision.upper()} model; re-export with"
                + (" --int8" if precision.startswith("int8") else "out --int8"),
            )
        return self.root / self.files[role].path


def write_manifest(
    root: str | Path, manifest: dict[str, Any], files: list[BundleFile], version: int = BUNDLE_VERSION
) -> dict[str, Any]:
    """Write ``manifest.json`` with the format header and the file list (atomically); returns what was written.

    ``version``: an older bundle given a file that does not depend on the newer contract keeps its version.
    """
    roles = [f.role for f in files]
    if len(set(roles)) != len(roles):
        raise ValueError(f"duplicate roles in bundle file list: {roles}")
    if not 1 <= version <= BUNDLE_VERSION:
        raise ValueError(f"bundle format version must be in 1..{BUNDLE_VERSION}, got {version}")
    body = {"format": BUNDLE_FORMAT, "format_version": version}
    body.update({k: v for k, v in manifest.items() if k not in ("format", "format_version", "files")})
    body["files"] = [f.as_dict() for f in files]
    write_json(Path(root) / MANIFEST_NAME, body)
    return body


def _safe_relative(manifest_path: Path, rel: Any) -> str:
    if not isinstance(rel, str) or not rel:
        raise InputError(manifest_path, f"file entry has no path: {rel!r}")
    p = PurePosixPath(rel)
    if p.is_absolute() or ".." in p.parts or "\\" in rel:
        raise InputError(manifest_path, f"file path {rel!r} leaves the bundle directory")
    return p.as_posix()


def _parse_files(manifest_path: Path, entries: Any) -> dict[str, BundleFile]:
    if not isinstance(entries, list):
        raise InputError(manifest_path, "'files' must be a list")
    files: dict[str, BundleFile] = {}
    for e in entries:
        try:
            f = BundleFile(
                role=str(e["role"]),
                path=_safe_relative(manifest_path, e["path"]),
                sha256=str(e["sha256"]).lower(),
                bytes=int(e["bytes"]),
            )
        except (KeyError, TypeError, ValueError):
            raise InputError(manifest_path, f"malformed file entry {e!r} (needs role, path, sha256, bytes)") from None
        if f.role in files:
            raise InputError(manifest_path, f"role '{f.role}' listed twice")
        files[f.role] = f
    return files


def verify_file(root: Path, f: BundleFile) -> None:
    """Size first (cheap, and names truncation), then sha256."""
    p = root / f.path
    if not p.is_file():
        raise InputError(p, "file listed in the bundle manifest is missing")
    size = p.stat().st_size
    if size != f.bytes:
        what = "truncated" if size < f.bytes else "larger than recorded"
        raise InputError(p, f"{what}: {size} bytes, manifest says {f.bytes}; re-copy or re-export the bundle")
    digest = sha256_of(p)
    if digest != f.sha256:
        raise InputError(
            p, f"sha256 {digest[:12]}... does not match the manifest ({f.sha256[:12]}...): file was modified"
        )


def read_manifest(bundle_dir: str | Path) -> tuple[Path, dict[str, Any]]:
    """The parsed manifest of a bundle directory, checked for format and version only."""
    root = Path(bundle_dir)
    if not root.is_dir():
        raise InputError(root, "bundle directory does not exist")
    mpath = root / MANIFEST_NAME
    if not mpath.is_file():
        raise InputError(mpath, "bundle has no manifest.json (not an acesplat bundle)")
    try:
        manifest = json.loads(mpath.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(mpath, f"manifest is not valid JSON ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != BUNDLE_FORMAT:
        raise InputError(mpath, f"not an {BUNDLE_FORMAT} manifest")
    version = manifest.get("format_version")
    if not isinstance(version, int) or version < 1:
        raise InputError(mpath, f"manifest has no valid format_version (got {version!r})")
    if version > BUNDLE_VERSION:
        raise InputError(
            mpath,
            f"bundle format version {version} is newer than this program supports ({BUNDLE_VERSION}); "
            "update acesplat-edge",
        )
    return mpath, manifest


def load_bundle(bundle_dir: str | Path, verify: bool = True, roles: list[str] | None = None) -> Bundle:
    """Open a bundle; with ``verify`` every listed file (or only ``roles``) is checked against the manifest."""
    root = Path(bundle_dir)
    mpath, manifest = read_manifest(root)
    files = _parse_files(mpath, manifest.get("files"))
    scr = manifest.get("scr")
    if scr is not None:
        try:
            h, w = (int(v) for v in scr["input_size"])
            int(scr["output_stride"])
        except (KeyError, TypeError, ValueError):
            raise InputError(mpath, "scr section needs input_size [H, W] and output_stride") from None
        if h <= 0 or w <= 0:
            raise InputError(mpath, f"scr input_size must be positive, got {scr['input_size']}")
        if int(scr["output_stride"]) not in (OUTPUT_STRIDE, DENSE_OUTPUT_STRIDE):
            raise InputError(
                mpath, f"scr output_stride must be {OUTPUT_STRIDE} or {DENSE_OUTPUT_STRIDE}, got {scr['output_stride']}"
            )
    if verify:
        for f in files.values():
            if roles is None or f.role in roles:
                verify_file(root, f)
    return Bundle(root=root, manifest=manifest, files=files)
