"""The buffer layout: one view at a time in, stacked out, and two buffers merged with their views kept apart."""

from __future__ import annotations

import numpy as np
import torch

from acesplat.core.geometry import invert_pose, make_pose
from acesplat.scr.buffer import BufferBuilder, merge_buffers


def one_view_buffer(seed: int, views: int) -> dict:
    rng = np.random.default_rng(seed)
    b = BufferBuilder()
    for v in range(views):
        f = torch.from_numpy(rng.normal(size=(4, 3, 5)).astype(np.float32))
        take = np.array([0, 7, 14])
        T = make_pose(np.eye(3), [v, seed, 0.0])
        targets = None if v % 2 else rng.normal(size=(3, 3))
        b.add_view(f, take, rng.uniform(0, 40, (3, 2)), T, np.eye(3) * (v + 1), targets)
        if v == 0:
            first = (f.reshape(4, -1)[:, take].T, T, targets)
    return b, first


def test_builder_stacks_the_chosen_cells_with_their_view() -> None:
    b, (feats0, T0, targets0) = one_view_buffer(0, 3)
    assert b.features == 9
    buf = b.build()
    assert buf["feats"].dtype == torch.float16 and buf["feats"].shape == (9, 4)
    torch.testing.assert_close(buf["feats"][:3].float(), feats0.half().float())
    assert buf["view"].tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    np.testing.assert_allclose(buf["w2c"][0].numpy(), invert_pose(T0)[:3], atol=1e-6)
    np.testing.assert_allclose(buf["target"][:3].numpy(), targets0, rtol=1e-6)
    assert torch.isnan(buf["target"][3:6]).all()  # a view without targets
    assert buf["K"].shape == (3, 3, 3) and float(buf["K"][2, 0, 0]) == 3.0
    assert BufferBuilder().build() is None


def test_merged_buffers_keep_each_cell_with_its_own_camera() -> None:
    a = one_view_buffer(0, 2)[0].build()
    b = one_view_buffer(1, 3)[0].build()
    m = merge_buffers(a, b)
    assert m["feats"].shape[0] == 15 and m["w2c"].shape[0] == 5
    # Every cell still points at the camera it came with.
    for src, rows in ((a, range(0, 6)), (b, range(6, 15))):
        for r in rows:
            torch.testing.assert_close(m["w2c"][m["view"][r]], src["w2c"][src["view"][r - rows[0]]])
    assert int(m["view"].max()) == 4
