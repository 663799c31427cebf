"""Stable resting poses of an object on a plane, computed once and cached.

A free rigid body on a plane rests on a face of the convex hull of its collision geometry
whose plane the centre of mass projects into. `stable_poses` computes those faces with
`trimesh.poses.compute_stable_poses` (quasi-static toppling from a uniformly random
orientation, no sampling of the centre of mass: deterministic) on the convex hull of the
object's collision meshes, with the centre of mass from the model data (`meta.json`
`com_m`), and gives each resting rotation its probability of being where a randomly
dropped object ends up.

Results are cached per object content (the collision meshes' bytes, the centre of mass
and `STABLE_POSES_VERSION`, hashed): in the process, and on disk under the object cache
(`$DRAKE_GRASP_CACHE/stable-poses-v<N>/<hash>.npz`, written atomically), so each object
is computed once per machine (0.03-0.2 s each) and a changed mesh is never served an old
answer.

`sample_stable_rotation` draws a resting rotation with its probability and turns it by a
uniformly random yaw: the scene sampler's `initial_pose: stable` (`world.scene`), which
lets the dataset's short settle start from rest instead of from a tumbling drop.
"""

from __future__ import annotations

import hashlib
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drake_grasp.objects.library import ObjectInfo, default_cache_root, visual_mesh

# Part of every cache key: bump when the computation changes.
STABLE_POSES_VERSION = 1
# Resting faces below this probability are dropped (a hull's sliver faces: the object
# would not stay there in physics either); the rest are renormalized.
MIN_PROBABILITY = 1e-3

_MEMO: dict[str, StablePoses] = {}


@dataclass(frozen=True)
class StablePoses:
    """An object's resting rotations R_WO (yaw 0) and their probabilities (sum 1),
    most probable first."""

    rotations: np.ndarray  # (P, 3, 3)
    probabilities: np.ndarray  # (P,)

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        """A resting rotation drawn with its probability, turned by a uniform yaw."""
        k = int(rng.choice(len(self.probabilities), p=self.probabilities))
        yaw = rng.uniform(-np.pi, np.pi)
        c, s = np.cos(yaw), np.sin(yaw)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return Rz @ self.rotations[k]


def collision_mesh_paths(info: ObjectInfo) -> list[Path]:
    """The local mesh files of the model's `<collision>` elements (in file order)."""
    root = ET.parse(info.model_path).getroot()
    paths = []
    for collision in root.iter("collision"):
        for mesh in collision.iter("mesh"):
            filename = mesh.get("filename") or ""
            if filename and "://" not in filename:
                paths.append(Path(info.model_path).parent / filename)
    return paths


def _centre_of_mass(info: ObjectInfo) -> np.ndarray:
    com = info.read_meta().get("com_m")
    if com is None:
        return None
    com = np.asarray(com, dtype=float)
    if com.shape != (3,) or not np.all(np.isfinite(com)):
        raise ValueError(f"{info.directory / 'meta.json'}: key 'com_m' has value "
                         f"{com.tolist()!r}; expected 3 finite numbers")
    return com


def content_key(info: ObjectInfo) -> str:
    """The cache key of an object's stable poses: a hash of its collision meshes' bytes
    (the visual mesh's when the model names no local collision mesh), its centre of mass
    and `STABLE_POSES_VERSION`."""
    h = hashlib.sha256(f"stable-poses/{STABLE_POSES_VERSION}".encode())
    paths = collision_mesh_paths(info) or [Path(info.directory) / "visual.obj"]
    for path in paths:
        h.update(path.read_bytes())
    com = _centre_of_mass(info)
    h.update(b"none" if com is None else np.round(com, 12).tobytes())
    return h.hexdigest()[:32]


def _hull_points(info: ObjectInfo) -> np.ndarray:
    import trimesh

    paths = collision_mesh_paths(info)
    if not paths:
        return np.asarray(visual_mesh(info).vertices, dtype=float)
    return np.vstack([np.asarray(trimesh.load(str(p), force="mesh", process=False).vertices,
                                 dtype=float) for p in paths])


def compute_stable_poses(info: ObjectInfo) -> StablePoses:
    """`trimesh.poses.compute_stable_poses` on the convex hull of the collision geometry,
    centre of mass from the model data (uncached; see `stable_poses`).

    Raises:
        ValueError: the object has no resting face (a centre of mass outside its hull),
            naming the object's folder.
    """
    import trimesh

    hull = trimesh.convex.convex_hull(_hull_points(info))
    com = _centre_of_mass(info)
    transforms, probs = trimesh.poses.compute_stable_poses(
        hull, center_mass=hull.center_mass if com is None else com, sigma=0.0, n_samples=1,
        seed=0)
    probs = np.asarray(probs, dtype=float)
    keep = probs >= MIN_PROBABILITY
    if not keep.any():
        raise ValueError(f"{info.directory}: no stable resting pose (is the centre of mass "
                         "com_m in meta.json inside the collision geometry?)")
    rotations = np.asarray(transforms, dtype=float)[keep, :3, :3]
    probs = probs[keep] / probs[keep].sum()
    # Most probable first, ties broken by the rotation's entries: one order everywhere.
    order = np.lexsort((*rotations.reshape(len(probs), 9).round(9).T[::-1], -probs.round(12)))
    return StablePoses(rotations[order], probs[order])


def _cache_dir() -> Path:
    return default_cache_root() / f"stable-poses-v{STABLE_POSES_VERSION}"


def stable_poses(info: ObjectInfo, *, cache_dir: str | Path | None = None) -> StablePoses:
    """The object's `StablePoses`, from the process's memo, the disk cache, or computed
    (then stored in both). `cache_dir`: the disk cache folder (default
    `$DRAKE_GRASP_CACHE/stable-poses-v<N>`)."""
    key = content_key(info)
    if key in _MEMO:
        return _MEMO[key]
    folder = Path(cache_dir) if cache_dir is not None else _cache_dir()
    path = folder / f"{key}.npz"
    poses = None
    if path.is_file():
        try:
            with np.load(path) as data:
                poses = StablePoses(np.array(data["rotations"]), np.array(data["probabilities"]))
        except (OSError, ValueError, KeyError):
            poses = None  # unreadable (a foreign or damaged file): computed again below
    if poses is None:
        poses = compute_stable_poses(info)
        try:
            folder.mkdir(parents=True, exist_ok=True)
            tmp = folder / f"{key}.{os.getpid()}.tmp.npz"
            np.savez(tmp, rotations=poses.rotations, probabilities=poses.probabilities)
            os.replace(tmp, path)
        except OSError:
            pass  # a read-only cache: the memo still holds it for this process
    _MEMO[key] = poses
    return poses


__all__ = ["MIN_PROBABILITY", "STABLE_POSES_VERSION", "StablePoses", "collision_mesh_paths",
           "compute_stable_poses", "content_key", "stable_poses"]
