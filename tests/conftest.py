"""Shared fixtures: the tiny analytic room, its tiny map and exported bundle, built once per session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> dict:
    """The tiny room (12 training views, 4 test views off the training trajectory), its map and FP32+INT8 bundle.

    Keys: root, scene, map, encoder, bundle, manifest (the export's manifest, with its self-checks).
    """
    from tests.test_edge_scene import tiny_setup

    return tiny_setup(tmp_path_factory.mktemp("tiny"))
