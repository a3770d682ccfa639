"""The bundle manifest: written and read back, and every way a copied bundle can go wrong is a one-line error."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from acesplat.core.bundle import (
    BUNDLE_VERSION,
    MANIFEST_NAME,
    ROLE_SCR_FP32,
    ROLE_SCR_INT8,
    describe_file,
    load_bundle,
    sha256_of,
    write_manifest,
)
from acesplat.core.errors import InputError


def _bundle(tmp_path: Path, extra_files: dict[str, str] | None = None) -> Path:
    root = tmp_path / "b"
    root.mkdir()
    (root / "scr.onnx").write_bytes(b"fp32 model bytes" * 100)
    (root / "scr.int8.onnx").write_bytes(b"int8 model" * 50)
    files = [describe_file(root, "scr.onnx", ROLE_SCR_FP32), describe_file(root, "scr.int8.onnx", ROLE_SCR_INT8)]
    for role, name in (extra_files or {}).items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(role.encode() * 10)
        files.append(describe_file(root, name, role))
    write_manifest(root, {"scene": {"name": "room"}, "scr": {"input_size": [240, 320], "output_stride": 8}}, files)
    return root


def _edit_manifest(root: Path, fn) -> None:
    m = json.loads((root / MANIFEST_NAME).read_text())
    fn(m)
    (root / MANIFEST_NAME).write_text(json.dumps(m))


def test_round_trip_and_generic_file_list(tmp_path: Path) -> None:
    root = _bundle(tmp_path, {"gaussians_ply": "splat/scene.ply"})
    b = load_bundle(root)
    assert b.input_size == (240, 320) and b.output_stride == 8 and b.scene_name == "room"
    assert b.scr_model("fp32") == root / "scr.onnx"
    assert b.path("gaussians_ply") == root / "splat" / "scene.ply"
    entry = b.files[ROLE_SCR_FP32]
    assert entry.bytes == 1600 and entry.sha256 == sha256_of(root / "scr.onnx")
    m = json.loads((root / MANIFEST_NAME).read_text())
    assert m["format_version"] == BUNDLE_VERSION and len(m["files"]) == 3


def test_tampered_file_is_rejected(tmp_path: Path) -> None:
    root = _bundle(tmp_path)
    data = bytearray((root / "scr.onnx").read_bytes())
    data[10] ^= 0xFF  # same size, different content
    (root / "scr.onnx").write_bytes(bytes(data))
    with pytest.raises(InputError, match="sha256.*modified") as e:
        load_bundle(root)
    assert "scr.onnx" in str(e.value) and "\n" not in str(e.value)


def test_truncated_file_is_rejected(tmp_path: Path) -> None:
    root = _bundle(tmp_path)
    data = (root / "scr.int8.onnx").read_bytes()
    (root / "scr.int8.onnx").write_bytes(data[:-7])
    with pytest.raises(InputError, match="truncated"):
        load_bundle(root)
    # only the files that will run are verified when asked
    assert load_bundle(root, roles=[ROLE_SCR_FP32]).has(ROLE_SCR_INT8)


def test_missing_file_and_missing_manifest(tmp_path: Path) -> None:
    root = _bundle(tmp_path)
    (root / "scr.onnx").unlink()
    with pytest.raises(InputError, match="missing"):
        load_bundle(root)
    (root / MANIFEST_NAME).unlink()
    with pytest.raises(InputError, match="no manifest"):
        load_bundle(root)
    with pytest.raises(InputError, match="does not exist"):
        load_bundle(tmp_path / "nowhere")


def test_newer_format_version_is_a_clear_error(tmp_path: Path) -> None:
    root = _bundle(tmp_path)
    _edit_manifest(root, lambda m: m.update(format_version=BUNDLE_VERSION + 1))
    with pytest.raises(InputError, match=f"version {BUNDLE_VERSION + 1} is newer.*update"):
        load_bundle(root)


def test_format_1_bundles_still_load_and_keep_their_version(tmp_path: Path) -> None:
    root = _bundle(tmp_path)
    _edit_manifest(root, lambda m: m.update(format_version=1))
    b = load_bundle(root)
    assert b.format_version == 1 and BUNDLE_VERSION == 2 and b.scr_model("fp32") == root / "scr.onnx"
    write_manifest(root, b.manifest, list(b.files.values()), version=b.format_version)
    assert load_bundle(root).format_version == 1  # a file added to an old bundle does not relabel it
    with pytest.raises(ValueError, match="1..2"):
        write_manifest(root, b.manifest, list(b.files.values()), version=BUNDLE_VERSION + 1)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda m: m.update(format="something-else"), "not an acesplat-bundle"),
        (lambda m: m["files"][0].update(path="../outside.onnx"), "leaves the bundle"),
        (lambda m: m["files"][0].update(path="/etc/passwd"), "leaves the bundle"),
        (lambda m: m["files"][0].pop("sha256"), "malformed file entry"),
        (lambda m: m["files"].append(dict(m["files"][0])), "listed twice"),
        (lambda m: m["scr"].update(input_size=[240]), "input_size"),
    ],
)
def test_malformed_manifests(tmp_path: Path, edit, message: str) -> None:
    root = _bundle(tmp_path)
    _edit_manifest(root, edit)
    with pytest.raises(InputError, match=message):
        load_bundle(root)


def test_not_json(tmp_path: Path) -> None:
    root = _bundle(tmp_path)
    (root / MANIFEST_NAME).write_text("{ not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_bundle(root)


def test_missing_precision_says_how_to_fix(tmp_path: Path) -> None:
    root = tmp_path / "b"
    root.mkdir()
    (root / "scr.onnx").write_bytes(b"x")
    write_manifest(
        root, {"scr": {"input_size": [8, 8], "output_stride": 8}}, [describe_file(root, "scr.onnx", ROLE_SCR_FP32)]
    )
    with pytest.raises(InputError, match="no INT8 model; re-export with --int8"):
        load_bundle(root).scr_model("int8")
