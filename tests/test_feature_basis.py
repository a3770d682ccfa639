"""The head trained on the features' principal components and folded back (acesplat/scr/feature_basis.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from acesplat.scr.feature_basis import fit_feature_basis, fold_head, project_features, reduced_head
from acesplat.scr.network import Head, HeadConfig


def _features(n: int, c: int, seed: int = 0) -> torch.Tensor:
    """(n, c) features with a decaying spectrum and a non-zero mean, as an encoder's are."""
    g = np.random.default_rng(seed)
    scales = 0.9 ** np.arange(c)
    x = g.normal(size=(n, c)) * scales @ np.linalg.qr(g.normal(size=(c, c)))[0] + g.normal(size=c)
    return torch.from_numpy(x.astype(np.float32))


def test_basis_and_kept_variance_match_a_numpy_pca() -> None:
    x = _features(5000, 24)
    fb = fit_feature_basis(x, 6)
    xn = x.numpy().astype(np.float64)
    cov = np.cov(xn, rowvar=False)
    evals, evecs = np.linalg.eigh(cov)
    evals, evecs = evals[::-1], evecs[:, ::-1]
    assert fb.kept_variance == pytest.approx(evals[:6].sum() / evals.sum(), rel=1e-6)
    np.testing.assert_allclose(fb.mean.numpy(), xn.mean(0), atol=1e-5)
    # The same subspace (the sign of each component is arbitrary).
    np.testing.assert_allclose(np.abs(fb.basis.numpy().T @ evecs[:, :6]), np.eye(6), atol=1e-4)
    np.testing.assert_allclose(fb.basis.numpy().T @ fb.basis.numpy(), np.eye(6), atol=1e-5)


def test_features_inside_a_subspace_are_recovered_exactly() -> None:
    g = np.random.default_rng(1)
    basis = np.linalg.qr(g.normal(size=(32, 5)))[0]
    mean = g.normal(size=32)
    x = torch.from_numpy((g.normal(size=(800, 5)) @ basis.T + mean).astype(np.float32))
    fb = fit_feature_basis(x, 5)
    assert fb.kept_variance == pytest.approx(1.0, abs=1e-6)
    z = project_features(x, fb)
    assert z.shape == (800, 5) and z.dtype == torch.float32
    np.testing.assert_allclose((z @ fb.basis.T + fb.mean).numpy(), x.numpy(), atol=1e-4)


def test_projection_keeps_the_buffer_dtype_and_works_in_chunks(monkeypatch) -> None:
    import acesplat.scr.feature_basis as fbm

    x = _features(1000, 16).half()
    fb = fit_feature_basis(x, 4)
    whole = project_features(x, fb)
    monkeypatch.setattr(fbm, "PROJECT_CHUNK", 97)
    chunked = project_features(x, fb)
    assert whole.dtype == torch.float16 and torch.equal(whole, chunked)
    ref = ((x.float() - fb.mean) @ fb.basis).half()
    assert torch.equal(whole, ref)


@pytest.mark.parametrize("dims", [8, 32])  # 32 == the head width: the skip is the coordinates themselves
def test_folded_head_gives_the_reduced_heads_outputs_on_full_features(dims: int) -> None:
    torch.manual_seed(0)
    x = _features(600, 64) * 0.3
    fb = fit_feature_basis(x, dims)
    cfg = HeadConfig(width=32, blocks=1)
    small = reduced_head(torch.tensor([0.5, -1.0, 2.0]), fb, cfg)
    assert small.in_channels == dims and isinstance(small.head_skip, torch.nn.Identity) == (dims == 32)
    with torch.no_grad():  # move the fresh head off its initialisation, as training would
        for p in small.parameters():
            p.add_(0.05 * torch.randn_like(p))
    full = fold_head(small, fb)
    assert full.in_channels == 64 and not isinstance(full.head_skip, torch.nn.Identity)
    with torch.no_grad():
        want = small.forward_points(project_features(x, fb))
        got = full.forward_points(x)
        got_conv = full(x.T[None, :, :, None])[0, :, :, 0].T  # the layout the export traces
    torch.testing.assert_close(got, want, atol=2e-4, rtol=1e-4)
    torch.testing.assert_close(got_conv, want, atol=2e-4, rtol=1e-4)
    # It is an ordinary head: its state dict loads into a fresh 64-channel head (the map file's path).
    again = Head(torch.zeros(3), in_channels=64, cfg=cfg)
    again.load_state_dict(full.state_dict())


def test_refusals() -> None:
    x = _features(100, 16)
    for dims in (0, 16, 17, -1):
        with pytest.raises(ValueError, match="dims must be between 1 and 15"):
            fit_feature_basis(x, dims)
    with pytest.raises(ValueError, match="expected features"):
        fit_feature_basis(x[0], 4)
    with pytest.raises(ValueError, match="at least 2"):
        fit_feature_basis(x[:1], 4)
    fb = fit_feature_basis(x, 4)
    with pytest.raises(ValueError, match=r"expected features \(N, 16\)"):
        project_features(x[:, :8], fb)
    with pytest.raises(ValueError, match="no input layer"):
        reduced_head(torch.zeros(3), fb, HeadConfig(width=16, blocks=1))
    with pytest.raises(ValueError, match="head takes 16 channels"):
        fold_head(Head(torch.zeros(3), in_channels=16, cfg=HeadConfig(width=8, blocks=1)), fb)


def test_mapping_on_components_returns_a_full_head_and_says_how_much_it_kept(tmp_path) -> None:
    from acesplat.core.scene import read_split
    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.mapping import MappingConfig, map_scene
    from acesplat.synth import synthesize

    scene = tmp_path / "scene"
    synthesize(scene, seed=3, train_frames=12, test_frames=2, size=(96, 128), supersample=1)
    enc, _ = load_encoder(None)
    cfg = MappingConfig(
        iterations=30,
        short_side=96,
        batch_size=256,
        buffer_size=3000,
        samples_per_image=150,
        precision="fp32",
        feature_dims=64,
        novel_views=4,
    )
    res = map_scene(read_split(scene, "train"), enc, cfg)
    assert res.head.in_channels == enc.cfg.out and res.feature_dims == 64
    assert 0.5 < res.kept_variance < 1.0
    assert res.iterations == 30 and res.novel_view_features > 0  # the novel views ran through the folded head
    with pytest.raises(ValueError, match="feature-dims must be 0 or between 1 and 511"):
        map_scene(read_split(scene, "train"), enc, MappingConfig(feature_dims=512))


def test_map_command_refuses_a_component_count_past_the_features(tmp_path) -> None:
    from typer.testing import CliRunner

    from acesplat.apps.cli import app
    from acesplat.synth import synthesize

    scene = tmp_path / "scene"
    synthesize(scene, seed=3, train_frames=4, test_frames=1, size=(48, 64), supersample=1)
    out = tmp_path / "m.pt"
    r = CliRunner().invoke(app, ["map", str(scene), "-o", str(out), "--feature-dims", "600"])
    assert r.exit_code == 2, r.output
    assert r.stderr.count("\n") == 1 and "--feature-dims must be 0 or between 1 and 511" in r.stderr
    assert not out.exists()
