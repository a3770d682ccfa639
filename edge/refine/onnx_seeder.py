"""Seeding through the bundle's initializer (feature adapter + init head, one ONNX graph).

The graph takes the encoder features the localizer's SCR graph output for the keyframe (bundle
format 2), so seeding costs the adapter and head only, not a second encoder run. It predicts
residuals around the same analytic start the SCR seeder uses (colour from the pixel, isotropic scale
covering the seeding gap, identity rotation, a prior opacity); it runs at the network input
resolution and its residuals are resampled to the refinement resolution. Centres stay the SCR depths
along pixel rays. The prior and the residual layout are acesplat/splatcore/head_io's, shared with Stage 2.

A format 1 bundle's initializer takes the image and runs its own encoder: it is not used (one line
says so) and refinement seeds from SCR coordinates.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from acesplat.core.bundle import Bundle, verify_file
from acesplat.core.config import knob_default
from acesplat.core.errors import InputError
from acesplat.core.gaussians import Gaussians
from acesplat.splatcore.bundle_section import INIT_INPUTS, ROLE_SPLAT_INIT
from acesplat.splatcore.head_io import (
    PRIOR_CHANNELS,
    SceneNorm,
    coordinate_prior,
    decode_residuals,
    residual_channels,
)
from acesplat.splatcore.lattice import seed_pixels
from acesplat.splatcore.pixel_coords import pixel_depths
from acesplat.splatcore.seeding import block_colours
from edge.inference import SessionSettings, create_session, session_options
from edge.refine.bundle_models import splat_section

CALIBRATION_RUNS = 3


class OnnxSeeder:
    """Callable with the refiner's seeder signature; needs keyframes with ``features`` and ``coords``."""

    needs_features = True
    """The refinement session asks the SCR graph for its features output when its seeder says this."""

    def __init__(
        self,
        model_path: str | Path,
        splat: dict,
        threads: int = 1,
        spacing: int = 2,
        provider: str = knob_default(SessionSettings, "provider"),
    ) -> None:
        self.path = Path(model_path)
        try:
            init = splat["init"]
            self.size = (int(init["input_size"][0]), int(init["input_size"][1]))
            self.opacity_prior = float(init["opacity_prior"])
            self.scale_prior = float(init["scale_prior"])
            self.head_degree = int(splat["head"]["sh_degree"])
            self.norm = SceneNorm.from_dict(splat["scene_norm"])
        except (KeyError, TypeError, ValueError):
            raise InputError(
                self.path, "bundle manifest's 'splat' section lacks the initializer's description"
            ) from None
        so = session_options(threads)
        self.provider = provider
        """The --provider name the initializer runs on."""
        self.sess = create_session(self.path, so, provider, "the initializer")
        names = [i.name for i in self.sess.get_inputs()]
        if tuple(names) != INIT_INPUTS:
            raise InputError(
                self.path, f"initializer takes {names}, expected {list(INIT_INPUTS)} (a bundle format 1 graph?)"
            )
        self.features_shape = tuple(int(d) for d in self.sess.get_inputs()[0].shape[1:])
        self.spacing = spacing
        self.channels = residual_channels(self.head_degree)

    def time_once(self, estimate=None, runs: int = CALIBRATION_RUNS) -> float:
        """Run the graph once on a blank input (loads it), then ``runs`` times timed; records the median seconds in
        ``estimate`` (the median: single runs on a shared CPU vary several-fold, bench/stage2.md) and returns it."""
        import time

        feats = np.zeros(self.features_shape, np.float32)
        prior = np.zeros((PRIOR_CHANNELS, *self.size), np.float32)
        self.residuals(feats, prior)
        times = []
        for _ in range(max(1, runs)):
            t0 = time.perf_counter()
            self.residuals(feats, prior)
            times.append(time.perf_counter() - t0)
        dt = float(np.median(times))
        if estimate is not None:
            estimate.record(dt)
        return dt

    def residuals(self, features: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """(H, W, K) head residuals for SCR features (C, h, w) and a prior (PRIOR_CHANNELS, H, W)."""
        if features.shape != self.features_shape:
            raise ValueError(f"features must have shape {self.features_shape}, got {features.shape}")
        feed = {
            INIT_INPUTS[0]: np.ascontiguousarray(features, dtype=np.float32)[None],
            INIT_INPUTS[1]: np.ascontiguousarray(prior, dtype=np.float32)[None],
        }
        out = self.sess.run(None, feed)[0]
        if out.shape != (1, self.channels, *self.size):
            raise InputError(
                self.path, f"initializer output {out.shape} is not (1, {self.channels}, {self.size[0]}, {self.size[1]})"
            )
        return np.ascontiguousarray(np.moveaxis(out[0], 0, -1))

    def __call__(self, kf, need: np.ndarray, max_new: int, sh_degree: int, rng: np.random.Generator) -> Gaussians:
        if kf.coords is None or kf.k_input is None or getattr(kf, "features", None) is None:
            return Gaussians.empty(sh_degree)
        if sh_degree < self.head_degree:
            raise ValueError(f"map SH degree {sh_degree} is below the initializer's {self.head_degree}")
        pix = pixel_depths(kf.coords, kf.pose, kf.k_input, kf.k)
        idx, s = seed_pixels(need & pix.valid, self.spacing, max_new, rng)
        if idx.size == 0:  # nothing to seed: skip the graph
            return Gaussians.empty(sh_degree)
        raw_in = self.residuals(kf.features, self.prior(kf))
        # One call over all channels (cv2 resizes up to 512 channels at once).
        raw = cv2.resize(raw_in, (kf.k.width, kf.k.height), interpolation=cv2.INTER_AREA).reshape(-1, raw_in.shape[2])
        return self.decode(
            raw[idx],
            block_colours(kf.rgb, float(s)).reshape(-1, 3)[idx],
            pix.centres.reshape(-1, 3)[idx],
            pix.depth.reshape(-1)[idx],
            0.5 * (kf.k.fx + kf.k.fy),
            float(s),
            sh_degree,
        )

    def prior(self, kf) -> np.ndarray:
        """The head's prior (PRIOR_CHANNELS, H, W) float32 at the network input size: rgb - 0.5, normalised
        world centres, log(depth / scale) (acesplat/splatcore/head_io.coordinate_prior), computed in float32."""
        k_in = kf.k_input
        pix = pixel_depths(kf.coords, kf.pose, k_in, k_in)
        rgb = cv2.resize(kf.rgb, (k_in.width, k_in.height), interpolation=cv2.INTER_LINEAR)
        return coordinate_prior(rgb, pix.centres, pix.depth, self.norm, float32_in_place=True)

    def decode(
        self,
        raw: np.ndarray,
        rgb: np.ndarray,
        centres: np.ndarray,
        depth: np.ndarray,
        focal_px: float,
        spacing_px: float,
        sh_degree: int,
    ) -> Gaussians:
        """Gaussians from residuals raw (N, C), colours (N, 3), centres (N, 3), camera depths (N,)."""
        return decode_residuals(
            raw, rgb, centres, depth, focal_px, spacing_px, self.head_degree, sh_degree,
            self.opacity_prior, self.scale_prior,
        )  # fmt: skip


def onnx_seeder_for(
    bundle: Bundle,
    threads: int = 1,
    spacing: int = 2,
    warn: Callable[[str], None] | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
) -> OnnxSeeder | None:
    """The bundle's initializer as a seeder, or None when the bundle has none or only a format 1 one (which runs
    its own encoder; ``warn`` gets one line): the SCR seeder is used then."""
    if not bundle.has(ROLE_SPLAT_INIT):
        return None
    if bundle.format_version < 2:
        if warn is not None:
            warn(
                f"{bundle.root}: bundle format {bundle.format_version}: its initializer runs its own encoder; seeding "
                "from SCR coordinates instead (re-export with `acesplat export MAP --splat SPLAT` to use it)"
            )
        return None
    f = bundle.files[ROLE_SPLAT_INIT]
    verify_file(bundle.root, f)
    return OnnxSeeder(bundle.root / f.path, splat_section(bundle), threads, spacing, provider)
