"""Witness views and the end-of-session repair (edge/refine/witness.py), the store's row origins, restore_view."""

from __future__ import annotations

import numpy as np
import pytest

from acesplat.core.gaussians import Gaussians
from acesplat.core.geometry import make_pose, rodrigues_to_matrix
from edge.refine.guard import psnr, view_mse
from edge.refine.refiner import RefineConfig, Refiner
from edge.refine.store import GaussianStore
from edge.refine.witness import Witness, WitnessPool, repair, viewpoint_distance
from tests.refine_scene import perturbed_map, rgb01, tiny_room

BLACK = np.zeros(3)


def _rows(n: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(
        rng.normal(size=(n, 3)).astype(np.float32),
        np.full((n, 3), -3.0, np.float32),
        np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        np.full(n, 2.0, np.float32),
        rng.uniform(size=(n, 1, 3)).astype(np.float32),
    )


def test_store_rows_keep_their_origin_through_appends_hides_and_compaction() -> None:
    g = _rows(40)
    st = GaussianStore(g, cap=1000)
    st.append(_rows(30, 1))  # past the spare capacity: the arrays grow
    st.hide(np.arange(0, 70, 3))
    st.compact()
    o = st.origin[: st.n]
    kept = [i for i in range(70) if i % 3]
    assert st.n == len(kept)
    assert o.tolist() == [i if i < 40 else -1 for i in kept]
    old = o >= 0
    np.testing.assert_array_equal(st.view.means[old], g.means[o[old]])


def _witness(f, pose=None) -> Witness:
    rgb = np.clip(rgb01(f) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return Witness(np.array(f.pose if pose is None else pose, np.float64), f.intrinsics, rgb, f.name)


def test_pool_keeps_distinct_viewpoints_when_full(tmp_path_factory) -> None:
    f = tiny_room(tmp_path_factory)[0]
    pool = WitnessPool(3)
    offsets = [0.0, 1.0, 0.001, 2.0]  # the third is nearly the first: the older of the two leaves
    for x in offsets:
        p = np.array(f.pose, np.float64)
        p[0, 3] += x
        pool.add(_witness(f, p))
    assert len(pool) == 3 and pool.offered == 4
    assert sorted(round(w.pose[0, 3] - f.pose[0, 3], 3) for w in pool.items) == [0.001, 1.0, 2.0]
    with pytest.raises(ValueError, match="uint8"):
        pool.add(Witness(f.pose, f.intrinsics, rgb01(f), "float image"))


def test_viewpoint_distance_by_hand() -> None:
    a = make_pose(np.eye(3), np.zeros(3))
    b = make_pose(rodrigues_to_matrix(np.array([0.0, np.radians(10.0), 0.0])), np.array([0.3, 0.0, 0.4]))
    assert viewpoint_distance(a, b) == pytest.approx(0.5 + 0.1, abs=1e-9)


def test_restore_view_puts_back_the_loaded_rows_of_a_view_and_hides_added_ones(tmp_path_factory) -> None:
    frames = tiny_room(tmp_path_factory)
    g = perturbed_map(frames[:4])
    r = Refiner(g, RefineConfig())
    st = r.store
    st.write_rows(np.arange(len(g)), g.subset(np.arange(len(g))))
    st.view.sh[:, 0] = 1.0 - st.view.sh[:, 0]  # spoil every colour
    st.hide(np.arange(0, len(g), 7))  # and remove some rows
    st.compact()
    st.append(_rows(50))  # and add some
    f = frames[1]
    restored, revived, hidden = r.restore_view(f.pose, f.intrinsics)
    assert restored > 0 and 0 < revived < restored
    target = rgb01(f)
    assert view_mse(r.map, f.pose, f.intrinsics, target, BLACK) == pytest.approx(
        view_mse(r.loaded, f.pose, f.intrinsics, target, BLACK), rel=1e-5
    )
    assert hidden > 0 and r.version == 1


def test_repair_leaves_no_witness_worse_than_the_loaded_map(tmp_path_factory) -> None:
    """A refined map that lowered some views (colours of one part spoiled, rows added in front of another) and
    raised others: after the repair no witness is below the loaded map."""
    frames = tiny_room(tmp_path_factory)
    g = perturbed_map(frames)
    r = Refiner(g, RefineConfig())
    truth = perturbed_map(frames, seed=5)  # a second, independent map: better on some views, worse on others
    st = r.store
    mix = np.zeros(len(g), bool)
    mix[: len(g) // 2] = True
    st.write_rows(np.flatnonzero(mix), truth.subset(np.flatnonzero(mix)))
    st.append(_rows(20, 3))
    witnesses = [_witness(f) for f in frames]
    before = [psnr(view_mse(r.loaded, f.pose, f.intrinsics, rgb01(f), BLACK)) for f in frames]
    rep = repair(r, witnesses, tolerance_db=0.0)
    after = [psnr(view_mse(r.map, f.pose, f.intrinsics, rgb01(f), BLACK)) for f in frames]
    assert rep["witnesses"] == len(frames) and rep["harmed_before"] >= 1
    assert all(a >= b - 1e-6 for a, b in zip(after, before))
    assert rep["worst_before_db"] < 0.0 and rep["ms"] > 0


def test_repair_falls_back_to_the_loaded_map_when_its_passes_run_out(tmp_path_factory) -> None:
    frames = tiny_room(tmp_path_factory)
    g = perturbed_map(frames[:4])
    r = Refiner(g, RefineConfig())
    r.store.view.sh[:, 0] = 1.0 - r.store.view.sh[:, 0]
    rep = repair(r, [_witness(f) for f in frames[:4]], tolerance_db=0.0, max_passes=0)
    assert rep["fell_back_to_loaded"] and rep["harmed_before"] >= 1
    np.testing.assert_array_equal(r.snapshot().sh, r.loaded.sh)


def test_pool_matches_a_brute_force_pool_over_a_long_run() -> None:
    """The kept distance matrix gives the same pool as recomputing every pair at every add."""
    from acesplat.core.camera import Intrinsics

    k = Intrinsics.from_focal(8.0, 8, 6)
    img = np.zeros((6, 8, 3), np.uint8)
    rng = np.random.default_rng(1)
    pool, ref = WitnessPool(5), []
    for i in range(60):
        pose = make_pose(rodrigues_to_matrix(rng.normal(0, 0.3, 3)), rng.normal(0, 1.0, 3))
        pool.add(Witness(pose, k, img, str(i)))
        ref.append(pose)
        if len(ref) > 5:
            pairs = [(viewpoint_distance(ref[a], ref[b]), a) for a in range(len(ref)) for b in range(a + 1, len(ref))]
            del ref[min(pairs)[1]]
    assert [w.pose.tobytes() for w in pool.items] == [p.tobytes() for p in ref]


def test_spread_picks_the_farthest_viewpoints_in_turn() -> None:
    from edge.refine.witness import spread

    poses = [make_pose(np.eye(3), np.array([x, 0.0, 0.0])) for x in (0.0, 0.1, 5.0, 2.3, 2.6)]
    assert spread(poses, 3) == [0, 2, 4]  # 0, the farthest (5 m), then 2.6 (2.4 m from both; 2.3 is 2.3)
    assert spread(poses, 10) == [0, 1, 2, 3, 4] and spread([], 3) == [] and spread(poses, 0) == []


def test_changed_rows_by_hand_and_an_unchanged_map_renders_no_witness(tmp_path_factory) -> None:
    from edge.refine.witness import changed_rows

    frames = tiny_room(tmp_path_factory)
    g = perturbed_map(frames[:2])
    r = Refiner(g, RefineConfig())
    rep = repair(r, [_witness(f) for f in frames[:4]], tolerance_db=0.0)
    assert rep["rendered"] == 0 and rep["harmed_before"] == 0 and rep["passes"] == 0
    st = r.store
    st.view.sh[3, 0, 0] += 0.5
    st.hide(np.array([5, 9]))
    st.compact()  # rows 5 and 9 are gone
    st.append(_rows(2))
    ch, lost = changed_rows(r)
    expect = np.zeros(st.n, bool)
    expect[3] = True
    expect[-2:] = True
    np.testing.assert_array_equal(ch, expect)
    assert lost.tolist() == [3, 5, 9]
