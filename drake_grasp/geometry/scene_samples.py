"""The scene geometry every ground-truth grasp test runs on (pure numpy / trimesh).

Owns the world-frame surface meshes of a scene's objects (`scene_meshes`, by a plain
numpy pose conversion), the area-weighted random surface samples drawn from them
(`ScenePoints`, `sample_scene_points`), the objects' masses and centres of mass
(`ObjectMasses`), and the argument checks (random generator, positive numbers and
integers, meshes) that the grasp sampling, checking and search modules share.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _check_rng(rng) -> None:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")


def _positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    v = float(value)
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        expected = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name}: expected a finite number {expected}, got {value!r}")
    return v


def _positive_int(name: str, value: int) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
    return int(value)


# ----------------------------------------------------------------------------
# Scene geometry.


def _quat_wxyz_to_matrix(quat_wxyz) -> np.ndarray:
    """Rotation matrix of a (w, x, y, z) quaternion (normalised first)."""
    q = np.asarray(quat_wxyz, dtype=float)
    n = np.linalg.norm(q) if q.shape == (4,) else 0.0
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"quat_wxyz: expected 4 finite numbers, not all zero, got {quat_wxyz!r}")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def scene_meshes(spec, library) -> list:
    """World-frame surface meshes (`visual.obj`) of a scene's objects, in spec order.

    Plain numpy pose conversion (the spec's xyz and quat_wxyz), so no Drake import.

    Args:
        spec: A `drake_grasp.world.scene.SceneSpec`.
        library: The `ObjectLibrary` the spec's object ids come from.

    Returns:
        One `trimesh.Trimesh` per object; index i is `spec.objects[i]`.
    """
    import trimesh

    from drake_grasp.objects import visual_mesh

    meshes = []
    for placement in spec.objects:
        info = library.get(placement.object_id)
        local = visual_mesh(info)
        R = _quat_wxyz_to_matrix(placement.quat_wxyz)
        t = np.asarray(placement.xyz, dtype=float)
        meshes.append(trimesh.Trimesh(np.asarray(local.vertices) @ R.T + t,
                                      np.asarray(local.faces), process=False))
    return meshes


def _check_meshes(meshes) -> list:
    meshes = list(meshes)
    for i, m in enumerate(meshes):
        if not hasattr(m, "faces") or not hasattr(m, "area_faces") or len(m.faces) == 0:
            raise ValueError(f"meshes[{i}]: expected a trimesh.Trimesh with faces, got {m!r}")
    return meshes


def _sample_faces(meshes, count: int, rng: np.random.Generator, face_mask=None):
    """Area-weighted random surface points of several meshes.

    Returns:
        (points (count, 3), outward face normals (count, 3), mesh index (count,)).
    """
    areas = np.concatenate([np.asarray(m.area_faces, dtype=float) for m in meshes])
    normals = np.concatenate([np.asarray(m.face_normals, dtype=float) for m in meshes])
    owner = np.concatenate([np.full(len(m.faces), i) for i, m in enumerate(meshes)])
    tris = np.concatenate([np.asarray(m.triangles, dtype=float) for m in meshes])
    weights = areas if face_mask is None else areas * face_mask(normals)
    total = weights.sum()
    if count == 0 or total <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    cdf = np.cumsum(weights)
    face = np.minimum(np.searchsorted(cdf, rng.random(count) * cdf[-1], side="right"), len(cdf) - 1)
    # Uniform barycentric coordinates (the square-root trick).
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    a, b, c = 1.0 - s, s * (1.0 - r2), s * r2
    T = tris[face]
    points = a[:, None] * T[:, 0] + b[:, None] * T[:, 1] + c[:, None] * T[:, 2]
    return points, normals[face], owner[face].astype(np.int64)


@dataclass(frozen=True)
class ScenePoints:
    """Dense object surface samples of a scene, the geometry every test runs on.

    Attributes:
        points: (P, 3) world positions [m].
        normals: (P, 3) outward unit surface normals.
        object_index: (P,) which mesh / scene object each point lies on.
    """

    points: np.ndarray
    normals: np.ndarray
    object_index: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def sample_scene_points(
    meshes, rng: np.random.Generator, *, spacing_m: float = 0.003
) -> ScenePoints:
    """Area-weighted random surface samples, about one per `spacing_m`^2 of surface.

    Surface samples suffice for the swept-volume collision test: a hand part inside an
    object must have passed through its surface on the way in. The spacing bounds
    the error of the measured widths and of the collision test (the thinnest hand
    part, a 16 mm finger, cannot slip between samples 3 mm apart).

    Args:
        meshes: World-frame `trimesh.Trimesh` objects (outward normals).
        rng: Source of randomness.
        spacing_m: Mean distance between neighbouring samples [m].
    """
    _check_rng(rng)
    meshes = _check_meshes(meshes)
    spacing = _positive("spacing_m", spacing_m)
    if not meshes:
        return ScenePoints(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    area = sum(float(m.area) for m in meshes)
    count = int(np.ceil(area / spacing**2))
    return ScenePoints(*_sample_faces(meshes, count, rng))


@dataclass(frozen=True)
class ObjectMasses:
    """Mass and world-frame centre of mass of each scene object (index as the meshes)."""

    mass_kg: np.ndarray  # (M,)
    com_W: np.ndarray  # (M, 3)

    @classmethod
    def of_scene(cls, spec, library) -> ObjectMasses:
        """From the objects' model data (`meta.json`: mass and centre of mass)."""
        mass, com = [], []
        for placement in spec.objects:
            meta = library.get(placement.object_id).read_meta()
            R = _quat_wxyz_to_matrix(placement.quat_wxyz)
            mass.append(float(meta["mass_kg"]))
            com.append(R @ np.asarray(meta["com_m"], dtype=float) + np.asarray(placement.xyz))
        return cls(np.asarray(mass, dtype=float).reshape(-1), np.asarray(com).reshape(-1, 3))

    @classmethod
    def of_meshes(cls, meshes, density_kg_m3: float = 500.0) -> ObjectMasses:
        """Uniform density: each (closed) mesh's volume centroid and volume x density."""
        mass = [abs(float(m.volume)) * density_kg_m3 if m.is_volume else 0.0 for m in meshes]
        com = [np.asarray(m.center_mass if m.is_volume else m.centroid, dtype=float)
               for m in meshes]
        return cls(np.asarray(mass, dtype=float), np.asarray(com).reshape(-1, 3))
