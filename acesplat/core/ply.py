"""The standard 3DGS Gaussian PLY: binary little-endian, one float32 property per parameter.

Layout (what the reference 3DGS code writes and common splat viewers read)::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1} opacity scale_0..2 rot_0..3

Values are pre-activation (log-scales, opacity logits, unnormalised wxyz quaternions). ``f_rest`` is
channel-major: all higher-order coefficients of R, then of G, then of B. Normals are written as
zeros and ignored on reading.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from acesplat.core.atomic import atomic_path
from acesplat.core.errors import InputError
from acesplat.core.gaussians import MAX_SH_DEGREE, Gaussians, sh_coeff_count

_FORMAT = "binary_little_endian 1.0"
_FLOAT_TYPES = ("float", "float32")
_MAX_HEADER_BYTES = 1 << 16


def ply_property_names(sh_degree: int) -> list[str]:
    """The exact vertex property list, in order, for a set of SH ``sh_degree``."""
    n_rest = 3 * (sh_coeff_count(sh_degree) - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_ply(path: str | Path, gaussians: Gaussians) -> None:
    """Write ``gaussians`` as a standard 3DGS PLY, atomically (a crash never leaves half a file)."""
    g = gaussians
    n = len(g)
    k = g.sh.shape[1]
    names = ply_property_names(g.sh_degree)
    rows = np.empty((n, len(names)), dtype="<f4")
    rows[:, 0:3] = g.means
    rows[:, 3:6] = 0.0
    rows[:, 6:9] = g.sh[:, 0, :]
    rest = 3 * (k - 1)
    # (N, K-1, 3) -> (N, 3, K-1): channel-major, as the reference implementation stores it.
    rows[:, 9 : 9 + rest] = np.transpose(g.sh[:, 1:, :], (0, 2, 1)).reshape(n, rest)
    rows[:, 9 + rest] = g.opacity_logits
    rows[:, 10 + rest : 13 + rest] = g.log_scales
    rows[:, 13 + rest : 17 + rest] = g.quats
    header = "ply\nformat " + _FORMAT + "\n" + f"element vertex {n}\n"
    header += "".join(f"property float {p}\n" for p in names) + "end_header\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(rows.tobytes())
            f.flush()
            os.fsync(f.fileno())


def read_ply(path: str | Path) -> Gaussians:
    """Read a standard 3DGS PLY into float32 Gaussians.

    Raises InputError naming the file and the offending property for a wrong format, a missing or
    extra property, a non-float property, truncated data or non-finite values.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot read PLY: {e.strerror or e}") from None
    n, names, body_start = _parse_header(path, data)
    _check_properties(path, names)
    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    k = n_rest // 3 + 1
    stride = 4 * len(names)
    body = data[body_start:]
    if len(body) < n * stride:
        raise InputError(path, f"PLY is truncated: {n} vertices need {n * stride} bytes, found {len(body)}")
    if len(body) > n * stride:
        raise InputError(path, f"PLY has {len(body) - n * stride} unexpected bytes after {n} vertices")
    table = np.frombuffer(body, dtype="<f4", count=n * len(names)).reshape(n, len(names))
    col = {p: i for i, p in enumerate(names)}
    for p, i in col.items():
        if p in ("nx", "ny", "nz"):
            continue
        if not np.all(np.isfinite(table[:, i])):
            raise InputError(path, f"property {p} has non-finite values")

    def cols(*ps: str) -> np.ndarray:
        return np.ascontiguousarray(table[:, [col[p] for p in ps]], dtype=np.float32)

    sh = np.empty((n, k, 3), np.float32)
    sh[:, 0, :] = cols("f_dc_0", "f_dc_1", "f_dc_2")
    if k > 1:
        rest = cols(*[f"f_rest_{i}" for i in range(n_rest)])
        sh[:, 1:, :] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    return Gaussians(
        means=cols("x", "y", "z"),
        log_scales=cols("scale_0", "scale_1", "scale_2"),
        quats=cols("rot_0", "rot_1", "rot_2", "rot_3"),
        opacity_logits=cols("opacity")[:, 0].copy(),
        sh=sh,
    )


def _parse_header(path: Path, data: bytes) -> tuple[int, list[str], int]:
    """(vertex count, property names in file order, byte offset of the body)."""
    marker = data.find(b"end_header\n", 0, _MAX_HEADER_BYTES)
    if not data.startswith(b"ply\n") or marker < 0:
        raise InputError(path, "not a PLY file (expected 'ply' and an 'end_header' line)")
    try:
        lines = data[:marker].decode("ascii").split("\n")[1:]
    except UnicodeDecodeError:
        raise InputError(path, "PLY header is not ASCII") from None
    n = None
    names: list[str] = []
    fmt = None
    for line in lines:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = " ".join(parts[1:])
            if fmt != _FORMAT:
                raise InputError(path, f"PLY format '{fmt}' is not supported; expected '{_FORMAT}'")
        elif parts[0] == "element":
            if len(parts) != 3 or parts[1] != "vertex" or n is not None:
                raise InputError(path, f"unexpected PLY element '{' '.join(parts[1:])}'; expected one 'vertex' element")
            try:
                n = int(parts[2])
            except ValueError:
                raise InputError(path, f"bad vertex count '{parts[2]}'") from None
            if n < 0:
                raise InputError(path, f"bad vertex count {n}")
        elif parts[0] == "property":
            if n is None:
                raise InputError(path, "PLY property before the vertex element")
            if len(parts) != 3:
                raise InputError(path, f"unsupported PLY property line '{line}'")
            dtype, name = parts[1], parts[2]
            if dtype not in _FLOAT_TYPES:
                raise InputError(path, f"property {name} has type {dtype}; expected float")
            if name in names:
                raise InputError(path, f"property {name} appears twice")
            names.append(name)
        else:
            raise InputError(path, f"unexpected PLY header line '{line}'")
    if fmt is None:
        raise InputError(path, "PLY header has no format line")
    if n is None:
        raise InputError(path, "PLY header has no vertex element")
    return n, names, marker + len(b"end_header\n")


def _check_properties(path: Path, names: list[str]) -> None:
    """The property set must be exactly the 3DGS one for some SH degree (order may differ)."""
    rest_idx = []
    for p in names:
        if p.startswith("f_rest_"):
            suffix = p[len("f_rest_") :]
            rest_idx.append(int(suffix) if suffix.isdigit() else 10**9)
    valid = [3 * (sh_coeff_count(d) - 1) for d in range(MAX_SH_DEGREE + 1)]
    wanted = max(len(rest_idx), max(rest_idx, default=-1) + 1)
    n_rest = next((v for v in valid if v >= wanted), valid[-1])
    expected = ply_property_names(valid.index(n_rest))
    have = set(names)
    missing = [p for p in expected if p not in have]
    if missing:
        raise InputError(path, f"PLY is missing property {missing[0]}" + _more(missing))
    extra = [p for p in names if p not in set(expected)]
    if extra:
        raise InputError(path, f"PLY has unexpected property {extra[0]}" + _more(extra))


def _more(items: list[str]) -> str:
    return f" (and {len(items) - 1} more)" if len(items) > 1 else ""
