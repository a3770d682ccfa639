"""The head trains on the buffer's features in their principal subspace, then is folded back to full width.

A scene's encoder features (C = 512 channels) lie close to a much smaller subspace. The head's two input layers
(``head_skip`` and ``res3_conv1``, C -> width each) are a third of a training step's multiply-accumulates; trained on
the features' first ``k`` principal components instead, they cost k / C of that. Because those layers are linear,
the trained head folds back exactly into a head that takes all C channels:

    W z + b,  z = B^T (x - m)   ==   (W B^T) x + (b - W B^T m)

so the map file, the export and the edge see the usual head. Only what the head sees during training changes: the
components past ``k`` (a small share of the variance, ``kept_variance`` says how small) are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from acesplat.scr.network import Head, HeadConfig

FIT_SAMPLES = 200_000
"""Buffered features the covariance is estimated from (enough for 512 channels many times over)."""
PROJECT_CHUNK = 262_144
"""Features projected at a time (bounds the float32 copy of a float16 buffer)."""


@dataclass(frozen=True)
class FeatureBasis:
    """mean (C,) and an orthonormal basis (C, k) of the features' first k principal components."""

    mean: torch.Tensor
    basis: torch.Tensor
    kept_variance: float
    """Share of the features' total variance inside the basis's span (on the fitted samples)."""

    @property
    def dims(self) -> int:
        return int(self.basis.shape[1])

    @property
    def channels(self) -> int:
        return int(self.basis.shape[0])


def fit_feature_basis(
    feats: torch.Tensor, dims: int, samples: int = FIT_SAMPLES, generator: torch.Generator | None = None
) -> FeatureBasis:
    """The first ``dims`` principal components of features (N, C), from at most ``samples`` of them."""
    if feats.dim() != 2:
        raise ValueError(f"expected features (N, C), got {tuple(feats.shape)}")
    n, c = feats.shape
    if not 0 < dims < c:
        raise ValueError(f"dims must be between 1 and {c - 1} for {c}-channel features, got {dims}")
    if n < 2:
        raise ValueError(f"need at least 2 features to fit a basis, got {n}")
    if n > samples:
        idx = torch.randperm(n, generator=generator)[:samples]
        feats = feats[idx]
    x = feats.to(torch.float64)
    mean = x.mean(0)
    xc = x - mean
    cov = xc.T @ xc / max(xc.shape[0] - 1, 1)
    evals, evecs = torch.linalg.eigh(cov)  # ascending
    evals = evals.flip(0).clamp(min=0.0)
    evecs = evecs.flip(1)
    total = float(evals.sum())
    kept = float(evals[:dims].sum()) / total if total > 0 else 1.0
    return FeatureBasis(mean.float(), evecs[:, :dims].float().contiguous(), kept)


def project_features(feats: torch.Tensor, fb: FeatureBasis) -> torch.Tensor:
    """Features (N, C) -> their coordinates (N, k) in the basis, centred, in the input's dtype."""
    if feats.dim() != 2 or feats.shape[1] != fb.channels:
        raise ValueError(f"expected features (N, {fb.channels}), got {tuple(feats.shape)}")
    mean, basis = fb.mean.to(feats.device), fb.basis.to(feats.device)
    out = torch.empty((feats.shape[0], fb.dims), dtype=feats.dtype, device=feats.device)
    for s in range(0, feats.shape[0], PROJECT_CHUNK):
        out[s : s + PROJECT_CHUNK] = ((feats[s : s + PROJECT_CHUNK].float() - mean) @ basis).to(feats.dtype)
    return out


def reduced_head(mean: torch.Tensor, fb: FeatureBasis, cfg: HeadConfig) -> Head:
    """A fresh head taking the basis coordinates (k,), to be trained and then folded with ``fold_head``."""
    if cfg.width == fb.channels:
        raise ValueError(
            f"a head of width {cfg.width} on {fb.channels}-channel features has no input layer to fold into"
        )
    return Head(mean, in_channels=fb.dims, cfg=cfg)


def fold_head(head: Head, fb: FeatureBasis) -> Head:
    """The head (trained on basis coordinates) as a head taking the full C-channel features: the same outputs
    for every feature, exactly up to float rounding."""
    if head.in_channels != fb.dims:
        raise ValueError(f"head takes {head.in_channels} channels, the basis has {fb.dims}")
    if head.cfg.width == fb.channels:
        raise ValueError(f"a head of width {head.cfg.width} has no input layer for {fb.channels} channels")
    full = Head(head.mean.view(3).detach().clone(), in_channels=fb.channels, cfg=head.cfg)
    sd = {k: v.detach().clone() for k, v in head.state_dict().items()}
    bt = fb.basis.T.to(torch.float64)  # (k, C)
    m = fb.mean.to(torch.float64)
    for name in ("head_skip", "res3_conv1"):
        layer = getattr(head, name)
        if isinstance(layer, torch.nn.Identity):  # k == width: the skip is z itself, i.e. B^T (x - m)
            w, b = torch.eye(fb.dims, dtype=torch.float64), torch.zeros(fb.dims, dtype=torch.float64)
        else:
            w, b = layer.weight.detach().flatten(1).to(torch.float64), layer.bias.detach().to(torch.float64)
        wf = w @ bt  # (width, C)
        sd[f"{name}.weight"] = wf.float().view(wf.shape[0], wf.shape[1], 1, 1)
        sd[f"{name}.bias"] = (b - wf @ m).float()
    full.load_state_dict(sd)
    full.train(head.training)
    return full.to(head.mean.device)
