"""Real photographs in pretraining: licences and evaluation sites refused by name, exact homography correspondences."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from acesplat.apps.cli import app
from acesplat.core.errors import InputError
from acesplat.scr import encoders
from acesplat.scr.network import Encoder, EncoderConfig
from acesplat.scr.photos import (
    ALLOWED_LICENCES,
    PhotoSource,
    check_source,
    folder_photos,
    load_photo_gray,
    photo_homography,
    photo_sources,
    photo_views,
)
from acesplat.scr.pretrain import PretrainConfig, install_default, make_photo_scene, pretrain

TINY = EncoderConfig(c1=4, c2=8, c3=8, c4=16, res2=16, out=16)


def _folder(tmp_path: Path, entries: list[dict], size: int = 300) -> Path:
    rng = np.random.default_rng(0)
    for e in entries:
        img = cv2.GaussianBlur(rng.integers(0, 256, (size, size + 40), dtype=np.uint8), (0, 0), 2.0)
        cv2.imwrite(str(tmp_path / e["file"]), img)
    (tmp_path / "photos.json").write_text(json.dumps({"photos": entries}))
    return tmp_path


def test_packaged_photographs_are_licensed_readable_and_not_evaluation_sites() -> None:
    srcs = photo_sources("packaged")
    assert len(srcs) >= 8 and len({s.name for s in srcs}) == len(srcs)
    for s in srcs:
        assert s.licence in ALLOWED_LICENCES and s.origin and s.subject
        assert min(load_photo_gray(s).shape) >= 256
        assert s.record()["path"] == s.path.name  # provenance names the file, not this machine's path
    assert photo_sources("none") == []


@pytest.mark.parametrize(
    "licence, subject, path, problem",
    [
        ("CC-BY-NC-4.0", "a street", "street.jpg", "licence 'CC-BY-NC-4.0' is not one of"),
        ("unknown", "a street", "street.jpg", "licence 'unknown'"),
        ("CC0-1.0", "Herz-Jesu church, Zurich", "church.jpg", "evaluation site 'herzjesu'"),
        ("CC0-1.0", "a square", "data/fountain11/rgb/0001.png", "evaluation site 'fountain'"),
        ("CC0-1.0", "a castle", "Strecha/castle-P30/img.jpg", "evaluation site 'strecha'"),
        ("public-domain", "a fox", "instant-ngp/data/nerf/fox/0001.jpg", "evaluation site 'instantngp'"),
    ],
)
def test_a_source_failing_its_licence_or_site_check_is_refused_by_name(licence, subject, path, problem) -> None:
    src = PhotoSource("mine:photo", Path(path), licence, "someone", subject)
    with pytest.raises(InputError) as e:
        check_source(src)
    assert "'mine:photo'" in str(e.value) and problem in str(e.value) and e.value.path == path


def test_a_folder_needs_a_manifest_that_lists_existing_files(tmp_path) -> None:
    with pytest.raises(InputError, match="photos.json: missing"):
        folder_photos(tmp_path)
    (tmp_path / "photos.json").write_text('{"photos": [{"file": "a.png"}]}')
    with pytest.raises(InputError, match="not a photo manifest"):
        folder_photos(tmp_path)
    entry = {"file": "a.png", "licence": "CC0-1.0", "origin": "me", "subject": "a wall"}
    (tmp_path / "photos.json").write_text(json.dumps({"photos": [entry]}))
    with pytest.raises(InputError, match="a.png: listed in .* but missing"):
        folder_photos(tmp_path)
    _folder(tmp_path, [entry])
    (src,) = photo_sources(str(tmp_path))
    assert src.name == f"{tmp_path.name}:a.png" and src.licence == "CC0-1.0"


def test_homography_maps_the_frame_centre_near_the_photograph_centre() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        H = photo_homography(rng, (240, 320), (480, 640))
        c = H @ np.array([160.0, 120.0, 1.0])
        # the frame centre lands within the shift bound (15% of the frame) of the photograph centre
        assert abs(c[0] / c[2] - 320) <= 0.15 * 320 + 1e-6 and abs(c[1] / c[2] - 240) <= 0.15 * 240 + 1e-6


def test_photo_views_coordinates_are_the_photograph_pixels_each_frame_shows() -> None:
    rng = np.random.default_rng(0)
    photo = cv2.GaussianBlur(rng.integers(0, 256, (300, 400), dtype=np.uint8), (0, 0), 3.0)
    photo = cv2.normalize(photo, None, 0, 255, cv2.NORM_MINMAX)
    unit = 0.01
    gray, coords = photo_views(photo, 3, 6, (120, 160), unit)
    assert gray.shape == (6, 120, 160) and gray.dtype == np.uint8 and coords.shape == (6, 120, 160, 3)
    k = 2.0 * 120 / 300  # PHOTO_SIDE_RATIO x frame height / the photograph's shorter side
    big = cv2.resize(photo, (round(400 * k), round(300 * k)), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    for f in range(6):
        on = np.isfinite(coords[f][..., 0])
        assert on.mean() > 0.5 and np.all(coords[f][on, 2] == 0)
        uv = (coords[f][on, :2] / unit).astype(np.float32)
        seen = cv2.remap(big, uv[:, 0].reshape(-1, 1), uv[:, 1].reshape(-1, 1), cv2.INTER_LINEAR)[:, 0]
        # the frame's gray levels are the photograph's at those coordinates, up to the gamma and blur of the frame
        r = np.corrcoef(seen, gray[f][on].astype(np.float64))[0, 1]
        assert r > 0.9, (f, r)
    scene = make_photo_scene(photo, 3, PretrainConfig(frames_per_scene=6, image_hw=(120, 160)))
    assert np.array_equal(scene.gray, gray) and scene.coords.dtype == np.float16  # pretraining's planar scene


def test_pretraining_with_photographs_records_them_and_starts_from_given_weights(tmp_path, monkeypatch) -> None:
    torch.manual_seed(0)
    entries = [{"file": f"p{i}.png", "licence": "CC0-1.0", "origin": "test", "subject": "noise"} for i in range(2)]
    (tmp_path / "photos").mkdir()
    folder = _folder(tmp_path / "photos", entries)
    init = tmp_path / "init.pt"
    torch.save(Encoder(TINY).state_dict(), init)
    cfg = PretrainConfig(
        scenes=1,
        frames_per_scene=8,
        image_hw=(136, 168),
        steps=2,
        encoder=TINY,
        photos=str(folder),
        photo_share=0.5,
        init_encoder=str(init),
    )
    out = tmp_path / "run"
    summary = pretrain(out, cfg, minutes=2.0, command="with photos")
    assert summary["finished"] and [p["path"] for p in summary["photos"]] == ["p0.png", "p1.png"]
    assert summary["init_encoder_sha256"] == encoders.file_sha256(init)
    monkeypatch.setattr(encoders, "DEFAULT_ENCODER", tmp_path / "weights" / "encoder_default.pt")
    provenance = json.loads(install_default(out, "install").with_suffix(".json").read_text())
    assert provenance["photos"][0]["licence"] == "CC0-1.0" and "2 photographs" in provenance["data"]


def test_cli_refuses_a_photograph_of_an_evaluation_site_in_one_line(tmp_path) -> None:
    entry = {"file": "a.png", "licence": "CC0-1.0", "origin": "me", "subject": "fountain-P11, EPFL"}
    folder = tmp_path / "photos"
    folder.mkdir()
    _folder(folder, [entry])
    out = tmp_path / "run"
    r = CliRunner().invoke(
        app, ["pretrain-encoder", str(out), "--photos", str(folder), "--steps", "1", "--scenes", "1", "--frames", "4"]
    )
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "a.png" in lines[0] and "evaluation site 'fountain'" in lines[0]
    assert not (out / "checkpoint.pt").exists() and not (out / "encoder.pt").exists()
