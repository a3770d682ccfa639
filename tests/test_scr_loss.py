"""The DSAC*/ACE loss and curriculum against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from acesplat.scr.loss import DEPTH_TARGET, curriculum_threshold, reprojection_loss
from acesplat.scr.mapping import one_cycle_lr


def test_curriculum_is_circular_from_50_to_1() -> None:
    assert curriculum_threshold(0.0) == pytest.approx(50.0)
    assert curriculum_threshold(1.0) == pytest.approx(1.0)
    # tau(0.6) = 1 + sqrt(1 - 0.36) * 49 = 1 + 0.8 * 49
    assert curriculum_threshold(0.6) == pytest.approx(1 + 0.8 * 49)
    vals = [curriculum_threshold(p) for p in np.linspace(0, 1, 11)]
    assert all(a >= b for a, b in zip(vals, vals[1:]))


def _camera() -> tuple[torch.Tensor, torch.Tensor]:
    K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
    w2c = torch.cat([torch.eye(3), torch.zeros(3, 1)], dim=1)
    return K, w2c


def test_valid_prediction_pays_tanh_clamped_reprojection_error() -> None:
    K, w2c = _camera()
    # A point at depth 2 that projects 3 px to the right of its pixel (50, 40): x = 3 * 2 / 100.
    pred = torch.tensor([[0.06, 0.0, 2.0]])
    parts = reprojection_loss(pred, w2c[None], K[None], torch.tensor([[50.0, 40.0]]), threshold=10.0)
    assert parts.valid_fraction == 1.0
    assert float(parts.loss) == pytest.approx(10.0 * math.tanh(3.0 / 10.0), rel=1e-5)


def test_invalid_prediction_is_pulled_to_fixed_depth_on_the_ray() -> None:
    K, w2c = _camera()
    pixel = torch.tensor([[70.0, 40.0]])
    pred = torch.tensor([[0.0, 0.0, -1.0]])  # behind the camera
    parts = reprojection_loss(pred, w2c[None], K[None], pixel, threshold=10.0)
    assert parts.valid_fraction == 0.0
    target = np.array([(70.0 - 50.0) / 100.0, 0.0, 1.0]) * DEPTH_TARGET
    assert float(parts.loss) == pytest.approx(np.linalg.norm(np.array([0.0, 0.0, -1.0]) - target), rel=1e-5)


@pytest.mark.parametrize(
    "pred",
    [[0.0, 0.0, 0.05], [0.0, 0.0, 2000.0], [30.0, 0.0, 2.0]],
    ids=["too-close", "too-far", "off-by-1500px"],
)
def test_invalid_cases(pred: list[float]) -> None:
    K, w2c = _camera()
    parts = reprojection_loss(torch.tensor([pred]), w2c[None], K[None], torch.tensor([[50.0, 40.0]]), 10.0)
    assert parts.valid_fraction == 0.0


def test_loss_is_mean_over_batch_and_differentiable() -> None:
    K, w2c = _camera()
    pred = torch.tensor([[0.06, 0.0, 2.0], [0.0, 0.0, -1.0]], requires_grad=True)
    pix = torch.tensor([[50.0, 40.0], [50.0, 40.0]])
    parts = reprojection_loss(pred, w2c[None].repeat(2, 1, 1), K[None].repeat(2, 1, 1), pix, 10.0)
    expected = (10.0 * math.tanh(0.3) + np.linalg.norm([0.0, 0.0, -1.0 - DEPTH_TARGET])) / 2
    assert float(parts.loss.detach()) == pytest.approx(expected, rel=1e-5)
    parts.loss.backward()
    assert torch.isfinite(pred.grad).all()


def test_one_cycle_rises_then_decays() -> None:
    assert one_cycle_lr(0.0, 1e-3, 1e-2) == pytest.approx(1e-3)
    assert one_cycle_lr(0.25, 1e-3, 1e-2) == pytest.approx(1e-2)
    assert one_cycle_lr(1.0, 1e-3, 1e-2) == pytest.approx(1e-5)
    assert one_cycle_lr(0.1, 1e-3, 1e-2) < one_cycle_lr(0.2, 1e-3, 1e-2)
    assert one_cycle_lr(0.5, 1e-3, 1e-2) > one_cycle_lr(0.9, 1e-3, 1e-2)
