"""Shared fixtures: the built-in object library in a per-session cache folder."""

import os

import numpy as np
import pytest


@pytest.fixture(scope="session")
def library(tmp_path_factory):
    from drake_grasp.objects import ObjectLibrary

    cache = os.environ.get("DRAKE_GRASP_CACHE")
    root = cache if cache else tmp_path_factory.mktemp("object_cache")
    return ObjectLibrary.builtin(cache_dir=root)


@pytest.fixture(scope="session")
def across_can():
    """`f(scene, library, offset_m=0.0)`: a top-down grasp at the centre of the lying
    can_000 of `scene`, closing across its axis; `offset_m` > 0 moves it that far beyond
    the can's side along the closing direction."""
    from pydrake.math import RigidTransform, RotationMatrix

    from drake_grasp.geometry.hand_model import topdown_rotation
    from drake_grasp.objects import visual_mesh

    def pose(scene, library, offset_m=0.0):
        X_WO = scene.objects[0].pose()
        R = X_WO.rotation().matrix()
        V = np.asarray(visual_mesh(library.get("can_000")).vertices) @ R.T + X_WO.translation()
        centre = 0.5 * (V.min(axis=0) + V.max(axis=0))
        axis = R[:, 2]
        yaw = np.arctan2(axis[1], axis[0]) + np.pi / 2
        R_WG = topdown_rotation(yaw)
        radius = 0.5 * float(V.max(axis=0)[2] - V.min(axis=0)[2])
        shift = (radius + offset_m) * R_WG[:, 0] if offset_m else np.zeros(3)
        return RigidTransform(RotationMatrix(R_WG), centre + shift)

    return pose


@pytest.fixture(scope="session")
def analysis_script():
    """`load(name)`: the module `analysis/<name>.py` (the analysis scripts are files, not
    a package), executed once per call."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "analysis"

    def load(name):
        spec = importlib.util.spec_from_file_location(name, root / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
