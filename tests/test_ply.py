"""Standard 3DGS PLY: exact layout, round trip, and every kind of bad file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from acesplat.core.errors import InputError
from acesplat.core.gaussians import Gaussians, sh_coeff_count
from acesplat.core.ply import ply_property_names, read_ply, write_ply


def _random(n: int, degree: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(
        rng.normal(size=(n, 3)).astype(np.float32),
        rng.normal(size=(n, 3)).astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32),
        rng.normal(size=n).astype(np.float32),
        rng.normal(size=(n, sh_coeff_count(degree), 3)).astype(np.float32),
    )


def _header_and_body(path: Path) -> tuple[list[str], bytes]:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end].decode("ascii").splitlines(), data[end:]


def _write_raw(
    path: Path,
    names: list[str],
    rows: np.ndarray,
    fmt: str = "binary_little_endian 1.0",
    types: dict[str, str] | None = None,
) -> None:
    types = types or {}
    header = f"ply\nformat {fmt}\nelement vertex {rows.shape[0]}\n"
    header += "".join(f"property {types.get(p, 'float')} {p}\n" for p in names) + "end_header\n"
    path.write_bytes(header.encode("ascii") + rows.astype("<f4").tobytes())


def test_exact_property_list_for_degree_3() -> None:
    names = ply_property_names(3)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(ply_property_names(0)) == 17


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_is_exact_and_layout_is_standard(tmp_path: Path, degree: int) -> None:
    g = _random(11, degree, seed=degree)
    path = tmp_path / "gaussians.ply"
    write_ply(path, g)
    header, body = _header_and_body(path)
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 11"]
    assert header[3:-1] == [f"property float {p}" for p in ply_property_names(degree)]
    assert header[-1] == "end_header"

    # The raw table: position, zero normals, dc, channel-major rest, opacity, scales, rotation.
    names = ply_property_names(degree)
    table = np.frombuffer(body, dtype="<f4").reshape(11, len(names))
    col = {p: i for i, p in enumerate(names)}
    np.testing.assert_array_equal(table[:, col["x"]], g.means[:, 0])
    np.testing.assert_array_equal(table[:, [col["nx"], col["ny"], col["nz"]]], 0.0)
    np.testing.assert_array_equal(table[:, col["f_dc_1"]], g.sh[:, 0, 1])
    k = sh_coeff_count(degree)
    for c in range(3):
        for j in range(k - 1):
            # f_rest_{c*(K-1)+j} is coefficient j+1 of channel c
            np.testing.assert_array_equal(table[:, col[f"f_rest_{c * (k - 1) + j}"]], g.sh[:, j + 1, c])
    np.testing.assert_array_equal(table[:, col["opacity"]], g.opacity_logits)
    np.testing.assert_array_equal(table[:, col["scale_2"]], g.log_scales[:, 2])
    np.testing.assert_array_equal(table[:, col["rot_0"]], g.quats[:, 0])

    back = read_ply(path)
    for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, f), getattr(g, f))
    assert back.dtype == np.float32


def test_reader_accepts_reordered_properties_and_comments(tmp_path: Path) -> None:
    g = _random(4, 1, seed=5)
    path = tmp_path / "a.ply"
    write_ply(path, g)
    names = ply_property_names(1)
    table = np.frombuffer(_header_and_body(path)[1], dtype="<f4").reshape(4, len(names))
    perm = np.random.default_rng(0).permutation(len(names))
    other = tmp_path / "reordered.ply"
    header = "ply\nformat binary_little_endian 1.0\ncomment written by another tool\nelement vertex 4\n"
    header += "".join(f"property float {names[i]}\n" for i in perm) + "end_header\n"
    other.write_bytes(header.encode() + np.ascontiguousarray(table[:, perm]).tobytes())
    back = read_ply(other)
    np.testing.assert_array_equal(back.sh, g.sh)
    np.testing.assert_array_equal(back.quats, g.quats)


def test_float64_set_is_written_as_float32(tmp_path: Path) -> None:
    g = _random(3, 0).astype(np.float64)
    write_ply(tmp_path / "g.ply", g)
    np.testing.assert_allclose(read_ply(tmp_path / "g.ply").means, g.means, rtol=1e-7)


def test_empty_set_round_trips(tmp_path: Path) -> None:
    write_ply(tmp_path / "e.ply", Gaussians.zeros(0, 2))
    e = read_ply(tmp_path / "e.ply")
    assert len(e) == 0 and e.sh_degree == 2


def test_write_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "g.ply"
    write_ply(path, _random(2, 0))
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("acesplat.core.ply.os.fsync", boom)
    with pytest.raises(OSError, match="disk full"):
        write_ply(path, _random(5, 3))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.ply"]


# --- bad input: one InputError naming the file and the problem ---------------------------------


def _good_rows(n: int, degree: int) -> tuple[list[str], np.ndarray]:
    names = ply_property_names(degree)
    return names, np.random.default_rng(1).normal(size=(n, len(names)))


def _expect(path: Path, *fragments: str) -> None:
    with pytest.raises(InputError) as e:
        read_ply(path)
    msg = str(e.value)
    assert str(path) in msg
    for f in fragments:
        assert f in msg, msg


def test_missing_property_is_named(tmp_path: Path) -> None:
    names, rows = _good_rows(3, 3)
    drop = names.index("f_rest_7")
    path = tmp_path / "missing.ply"
    _write_raw(path, names[:drop] + names[drop + 1 :], np.delete(rows, drop, axis=1))
    _expect(path, "missing property f_rest_7")
    drop = names.index("rot_3")
    _write_raw(path, names[:drop] + names[drop + 1 :], np.delete(rows, drop, axis=1))
    _expect(path, "missing property rot_3")


def test_extra_property_is_named(tmp_path: Path) -> None:
    names, rows = _good_rows(3, 0)
    path = tmp_path / "extra.ply"
    _write_raw(path, names + ["red"], np.concatenate([rows, rows[:, :1]], axis=1))
    _expect(path, "unexpected property red")
    names3, rows3 = _good_rows(2, 3)
    _write_raw(path, names3 + ["f_rest_45"], np.concatenate([rows3, rows3[:, :1]], axis=1))
    _expect(path, "unexpected property f_rest_45")


def test_wrong_format_and_types(tmp_path: Path) -> None:
    names, rows = _good_rows(2, 0)
    path = tmp_path / "bad.ply"
    _write_raw(path, names, rows, fmt="ascii 1.0")
    _expect(path, "format 'ascii 1.0' is not supported")
    _write_raw(path, names, rows, fmt="binary_big_endian 1.0")
    _expect(path, "binary_big_endian")
    _write_raw(path, names, rows, types={"opacity": "double"})
    _expect(path, "property opacity has type double")
    path.write_bytes(b"not a ply at all")
    _expect(path, "not a PLY file")
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement face 3\nproperty float x\nend_header\n")
    _expect(path, "unexpected PLY element 'face 3'")
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    _expect(path, "unsupported PLY property line")


def test_duplicate_truncated_trailing_and_nonfinite(tmp_path: Path) -> None:
    names, rows = _good_rows(3, 0)
    path = tmp_path / "bad.ply"
    _write_raw(path, names + ["x"], np.concatenate([rows, rows[:, :1]], axis=1))
    _expect(path, "property x appears twice")
    _write_raw(path, names, rows)
    path.write_bytes(path.read_bytes()[:-5])
    _expect(path, "truncated")
    _write_raw(path, names, rows)
    path.write_bytes(path.read_bytes() + b"\0\0\0\0")
    _expect(path, "unexpected bytes")
    rows[1, names.index("scale_1")] = np.nan
    _write_raw(path, names, rows)
    _expect(path, "property scale_1 has non-finite values")


def test_missing_file(tmp_path: Path) -> None:
    _expect(tmp_path / "nope.ply", "cannot read PLY")
