"""Adapting the encoder to a scene: the correspondences it learns from, against analytic references, and the command
end to end on the tiny room (its weights change, the file loads safely, the provenance names the inputs; bad input is
one line and exit 2 with nothing written)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from acesplat.apps.cli import app
from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import make_pose, rodrigues_to_matrix, transform_points
from acesplat.core.grid import cell_centers
from acesplat.scr.adapt import AdaptConfig, adapt_encoder, pixel_coordinates, view_coordinates
from acesplat.scr.encoders import load_encoder
from acesplat.scr.pretrain import PretrainScene

K = Intrinsics(60.0, 60.0, 39.5, 31.5, 80, 64)


def plane_cells(pose: np.ndarray, depth: float = 3.0) -> np.ndarray:
    """World coordinates (8, 10, 3) of the cells of K's 64x80 image seeing a fronto-parallel wall ``depth`` ahead."""
    uv = cell_centers(8, 10)
    return transform_points(pose, K.unproject(uv, np.full(len(uv), depth))).reshape(8, 10, 3)


def test_view_coordinates_drop_exactly_the_cells_that_do_not_reproject() -> None:
    pose = make_pose(rodrigues_to_matrix(np.radians([3.0, -5.0, 1.0])), [0.2, -0.1, 0.3])
    cells = plane_cells(pose)
    moved = cells.copy()
    moved[2, 3] += pose[:3, 0] * 3.0 * 5.0 / K.fx  # 5 px sideways at 3 m
    moved[5, 7] += pose[:3, 1] * 3.0 * 3.0 / K.fx  # 3 px
    out = view_coordinates(moved, pose, K.K, max_error_px=4.0)
    bad = ~np.isfinite(out[..., 0])
    assert bad.sum() == 1 and bad[2, 3]
    np.testing.assert_allclose(out[~bad], moved[~bad], atol=1e-6)
    assert (~np.isfinite(view_coordinates(moved, pose, K.K, max_error_px=2.0)[..., 0])).sum() == 2


@pytest.mark.parametrize("stride", [8, 4])
def test_pixel_coordinates_are_linear_on_a_wall_between_the_cells(stride: int) -> None:
    h, w = (64 - 4) // stride + 1, (80 - 4) // stride + 1
    uv = cell_centers(h, w, stride)
    cells = K.unproject(uv, np.full(len(uv), 3.0)).reshape(h, w, 3).astype(np.float32)
    px = pixel_coordinates(cells, 64, 80, stride)
    ys, xs = np.mgrid[4:60, 4:76]  # between the outermost cell centres a wall's coordinates are linear in the pixel
    truth = K.unproject(np.stack([xs.ravel(), ys.ravel()], 1).astype(float), np.full(xs.size, 3.0))
    np.testing.assert_allclose(px[4:60, 4:76].reshape(-1, 3), truth, atol=1e-5)


def test_pixel_coordinates_take_the_nearest_cell_next_to_a_hole() -> None:
    cells = plane_cells(np.eye(4)).astype(np.float32)
    holed = cells.copy()
    holed[3, 4] = np.nan
    near = pixel_coordinates(holed, 64, 80)
    assert not np.isfinite(near[28, 36]).all()  # the hole's own centre pixel
    assert np.isfinite(near[28, 30]).all()  # next to it: the nearest valid cell's coordinate
    np.testing.assert_allclose(near[28, 30], cells[3, 3], atol=1e-6)


def test_adapting_changes_the_weights_and_records_the_loss() -> None:
    rng = np.random.default_rng(0)
    views = 5
    gray = rng.integers(0, 255, (views, 64, 80), dtype=np.uint8)
    coords = np.repeat(pixel_coordinates(plane_cells(np.eye(4)).astype(np.float32), 64, 80)[None], views, 0)
    enc, _ = load_encoder()
    before = {k: v.clone() for k, v in enc.state_dict().items()}
    s = adapt_encoder(enc, PretrainScene(gray, (coords * 20).astype(np.float16), np.zeros(3)), AdaptConfig(steps=3))
    assert s["history"][-1]["step"] == 3 and np.isfinite(s["history"][-1]["loss"])
    assert any(not torch.equal(before[k], v) for k, v in enc.state_dict().items())
    with pytest.raises(ValueError, match="at least 3 views"):
        adapt_encoder(enc, PretrainScene(gray[:2], coords[:2].astype(np.float16), np.zeros(3)), AdaptConfig(steps=1))


def test_the_command_writes_a_loadable_encoder_with_its_provenance(tiny, tmp_path: Path) -> None:
    out = tmp_path / "adapted.pt"
    r = CliRunner().invoke(
        app,
        [
            "adapt-encoder",
            str(tiny["map"]),
            str(tiny["scene"]),
            "-o",
            str(out),
            "--steps",
            "3",
            "--json",
            str(tmp_path / "r.json"),
        ],
    )
    assert r.exit_code == 0, r.output
    enc, ident = load_encoder(out)
    orig, _ = load_encoder(tiny["encoder"])
    assert any(not torch.equal(a, b) for a, b in zip(enc.state_dict().values(), orig.state_dict().values()))
    prov = json.loads(out.with_suffix(".json").read_text())
    assert prov["encoder_sha256"] == ident.sha256 and prov["views"] == 12 and len(prov["train_images"]) == 12
    assert prov["from_encoder"]["sha256"] == json.loads((tmp_path / "r.json").read_text())["from_encoder"]["sha256"]
    assert prov["history"][-1]["step"] == 3 and 0 < prov["cells_kept"] <= 1


def test_bad_input_is_one_line_and_exit_2_with_nothing_written(tiny, tmp_path: Path) -> None:
    out = tmp_path / "adapted.pt"
    cases = [
        ([str(tmp_path / "missing.map.pt"), str(tiny["scene"])], "missing.map.pt"),
        ([str(tiny["map"]), str(tiny["scene"]), "--max-error-px", "1e-9"], "training views"),
        ([str(tiny["map"]), str(tiny["scene"]), "--lr", "0"], "--lr"),
    ]
    for args, needle in cases:
        r = CliRunner().invoke(app, ["adapt-encoder", *args, "-o", str(out), "--steps", "1"])
        assert r.exit_code == 2, r.output
        assert needle in r.output and "Traceback" not in r.output
        assert not out.exists() and not out.with_suffix(".json").exists()
