"""`acesplat pose`: pose a folder of one's own images with pycolmap and write the ACE layout."""

from __future__ import annotations

import enum
from pathlib import Path

import typer

from acesplat.apps.support import PhaseProgress, one_line_errors, option, report_json
from acesplat.importers.common import ImportConfig
from acesplat.importers.sfm import CAMERA_MODELS, MATCHERS, METADATA_FILE, PoseConfig, pose_images

Matcher = enum.Enum("Matcher", {m: m for m in MATCHERS}, type=str)
CameraModel = enum.Enum("CameraModel", {m: m for m in CAMERA_MODELS}, type=str)


@one_line_errors
def pose_command(
    images_dir: Path = typer.Argument(..., help="Folder of images (the files directly in it; natural name order)."),
    out: Path = typer.Option(..., "-o", "--out", help="Scene folder to create (must be new or empty)."),
    matcher: Matcher = option(PoseConfig, "matcher", "--matcher"),
    camera_model: CameraModel = option(PoseConfig, "camera_model", "--camera-model"),
    single_camera: bool = option(PoseConfig, "single_camera", "--single-camera/--per-image-camera"),
    overlap: int = option(PoseConfig, "overlap", "--overlap", min=1),
    max_features: int = option(PoseConfig, "max_features", "--max-features", min=16),
    seed: int = option(PoseConfig, "seed", "--seed"),
    scale_from: tuple[str, str, float] | None = typer.Option(
        None,
        "--scale-from",
        metavar="IMG_A IMG_B METRES",
        help="Two images (file names) whose cameras are METRES apart: the poses are rescaled to metres. "
        f"Without it COLMAP's arbitrary units are kept ({METADATA_FILE} says so).",
    ),
    test_every: int = option(ImportConfig, "test_every", "--test-every", min=0),
    json_out: Path | None = typer.Option(
        None, "--json", help="Write the counts (images, registered, points, reprojection error, scale, seconds)."
    ),
) -> None:
    """Pose images with pycolmap on CPU (SIFT, matching, incremental mapping) and write an ACE scene."""
    config = PoseConfig(
        matcher=Matcher(matcher).value, camera_model=CameraModel(camera_model).value, single_camera=single_camera,
        overlap=overlap, max_features=max_features, seed=seed,
    )  # fmt: skip
    if scale_from is not None and all(v is None for v in scale_from):
        scale_from = None  # typer hands an unset tuple option over as a tuple of Nones
    with PhaseProgress("pose ") as progress:
        summary = pose_images(images_dir, out, config, scale_from=scale_from, test_every=test_every, progress=progress)
    print(
        f"posed {summary.registered} of {summary.images} images ({summary.matcher} matching, {summary.camera_model}) "
        f"-> {summary.scene} in {summary.seconds:.1f} s"
    )
    print(
        f"  {summary.points} points, mean reprojection error {summary.mean_reprojection_error_px:.3f} px; "
        f"train {summary.train}, test {summary.test}: {summary.split_rule}"
    )
    if summary.units == "metres":
        sf = summary.scale_from or {}
        print(
            f"  units: metres (x{summary.scale:.6g}, {sf.get('image_a')} to {sf.get('image_b')} = {sf.get('metres')} m)"
        )
    else:
        print(f"  units: arbitrary (COLMAP's; pass --scale-from IMG_A IMG_B METRES for metres), see {METADATA_FILE}")
    if summary.undistorted:
        print(f"  undistorted {summary.undistorted} images with OpenCV")
    if summary.unregistered:
        shown = ", ".join(summary.unregistered[:10]) + (", ..." if len(summary.unregistered) > 10 else "")
        print(f"  {len(summary.unregistered)} images not registered (no pose, left out): {shown}")
    report_json(json_out, summary.as_dict())
