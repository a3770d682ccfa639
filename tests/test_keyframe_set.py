"""The keyframe file a bundle carries: a lossless round trip (depth to float16), and one-line refusals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from acesplat.align.keyframe_align import Keyframe
from acesplat.align.keyframe_set import KeyframeSet, load_keyframes, save_keyframes
from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError
from acesplat.core.geometry import look_at


def small_set(n: int = 3) -> KeyframeSet:
    rng = np.random.default_rng(0)
    K = Intrinsics(50.0, 51.0, 20.0, 15.0, 40, 30)
    kfs = [
        Keyframe(
            rng.integers(0, 256, (30, 40), dtype=np.uint8),
            K,
            look_at(np.array([i * 0.5, 0.0, 0.0]), np.array([i * 0.5, 0.0, 5.0])),
            rng.uniform(1.0, 5.0, (7, 10)).astype(np.float32),
            4,
        )
        for i in range(n)
    ]
    return KeyframeSet.stack(kfs)


def test_round_trip_keeps_images_poses_and_depth_to_float16(tmp_path: Path) -> None:
    ks = small_set()
    save_keyframes(tmp_path / "k.npz", ks)
    back = load_keyframes(tmp_path / "k.npz")
    assert len(back) == 3 and back.stride == 4
    assert np.array_equal(back.gray, ks.gray) and np.array_equal(back.c2w, ks.c2w) and np.array_equal(back.K, ks.K)
    assert np.allclose(back.depth, ks.depth, rtol=1e-3)
    kf = back.keyframe(1)
    assert kf.intrinsics == Intrinsics(50.0, 51.0, 20.0, 15.0, 40, 30)
    assert [np.allclose(k.c2w, ks.c2w[i]) for i, k in zip((1, 0, 2), back.near(ks.c2w[1], k=3))] == [True] * 3


def write(path: Path, **over) -> Path:
    ks = small_set()
    arrays = {"gray": ks.gray, "depth": ks.depth, "c2w": ks.c2w, "K": ks.K, "stride": np.int64(4)}
    arrays.update(over)
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "over, message",
    [
        ({"c2w": np.stack([np.eye(4), np.eye(4) * 2, np.eye(4)])}, "keyframe 1: pose"),
        ({"c2w": np.stack([np.eye(4), np.full((4, 4), np.nan), np.eye(4)])}, "non-finite"),
        ({"K": np.stack([np.diag([0.0, 50.0, 1.0])] * 3)}, "focal length"),
        ({"depth": np.ones((2, 7, 10))}, "3 images but depth"),
        ({"depth": np.ones((3, 2, 2))}, "does not cover"),
        ({"gray": np.zeros((3, 30, 40), np.float32)}, "uint8"),
        ({"stride": np.int64(5)}, "stride must be"),
    ],
)
def test_malformed_files_are_refused_naming_the_file(tmp_path: Path, over: dict, message: str) -> None:
    p = write(tmp_path / "bad.npz", **over)
    with pytest.raises(InputError, match=message) as e:
        load_keyframes(p)
    assert str(p) in str(e.value)


def test_missing_pickled_and_garbage_files_are_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        load_keyframes(tmp_path / "none.npz")
    np.savez(
        tmp_path / "obj.npz",
        gray=np.array([{"a": 1}], dtype=object),
        depth=np.ones(1),
        c2w=np.ones(1),
        K=np.ones(1),
        stride=np.int64(4),
    )
    with pytest.raises(InputError, match="not a keyframe file"):
        load_keyframes(tmp_path / "obj.npz")  # object arrays would need unpickling: refused
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a keyframe file"):
        load_keyframes(tmp_path / "junk.npz")
    np.savez(tmp_path / "part.npz", gray=np.zeros((1, 4, 4), np.uint8))
    with pytest.raises(InputError, match="not a keyframe file"):
        load_keyframes(tmp_path / "part.npz")


def test_a_failed_write_leaves_the_old_file(tmp_path: Path, monkeypatch) -> None:
    p = tmp_path / "k.npz"
    save_keyframes(p, small_set(2))
    before = p.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(OSError):
        save_keyframes(p, small_set(3))
    assert p.read_bytes() == before and [q.name for q in tmp_path.iterdir()] == ["k.npz"]
