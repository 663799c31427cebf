"""Convex building blocks, mass properties and OBJ output for object models.

Every object is a small set of convex parts. Each part is its own collision
geometry (a Drake `Convex`), so everything here keeps parts convex: primitives
are built as convex hulls of point sets, which also makes them watertight with
outward normals (what trimesh's mass properties need).

Units are metres and kilograms throughout.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drake_grasp.core.lazy import lazy_import

trimesh = lazy_import("trimesh")  # loaded when first used

# Facets per full circle: enough for a smooth depth silhouette at grasping
# distance, few enough that hydroelastic convex meshes stay cheap.
CIRCLE_SECTIONS = 24


@dataclass(frozen=True)
class Part:
    """One convex piece of an object.

    Attributes:
        name: Short label (for debugging and meta.json).
        mesh: Convex, watertight mesh in the object frame (metres).
        density_kg_m3: Density of this piece; mass = density * volume.
    """

    name: str
    mesh: trimesh.Trimesh
    density_kg_m3: float


@dataclass(frozen=True)
class MassProperties:
    """Rigid-body mass properties of a set of parts.

    Attributes:
        mass_kg: Total mass.
        volume_m3: Sum of the parts' volumes (the basis of `mass_kg`).
        com_m: Centre of mass in the object frame.
        inertia_kg_m2: 3x3 inertia tensor about the COM, object-frame axes
            (tensor convention: off-diagonals are -integral(x*y dm), as SDFormat
            and Drake expect).
    """

    mass_kg: float
    volume_m3: float
    com_m: np.ndarray
    inertia_kg_m2: np.ndarray


# ----------------------------------------------------------------------------
# Primitives. All return convex hull meshes.


def hull(points: np.ndarray) -> trimesh.Trimesh:
    """The convex hull of `points` (N x 3) as a watertight mesh."""
    points = np.asarray(points, dtype=float)
    mesh = trimesh.convex.convex_hull(points)
    if mesh.volume <= 0:
        raise ValueError(f"degenerate convex part from {len(points)} points")
    return mesh


def circle(radius: float, sections: int = CIRCLE_SECTIONS) -> np.ndarray:
    """`sections` points of a circle of `radius` in the xy-plane (N x 2)."""
    angles = np.arange(sections) * (2.0 * np.pi / sections)
    return radius * np.column_stack([np.cos(angles), np.sin(angles)])


def box(extents: tuple[float, float, float], center=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    """Axis-aligned box with the given full `extents`, centred at `center`."""
    half = 0.5 * np.asarray(extents, dtype=float)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return hull(corners * half + np.asarray(center, dtype=float))


def frustum_z(
    r_bottom: float,
    r_top: float,
    z_bottom: float,
    z_top: float,
    center_xy=(0.0, 0.0),
    sections: int = CIRCLE_SECTIONS,
) -> trimesh.Trimesh:
    """A (truncated) cone along z; equal radii give a cylinder."""
    cx, cy = center_xy
    bottom = circle(r_bottom, sections)
    top = circle(r_top, sections)
    points = np.vstack(
        [
            np.column_stack([bottom[:, 0] + cx, bottom[:, 1] + cy, np.full(sections, z_bottom)]),
            np.column_stack([top[:, 0] + cx, top[:, 1] + cy, np.full(sections, z_top)]),
        ]
    )
    return hull(points)


def cylinder_z(radius: float, z_bottom: float, z_top: float, center_xy=(0.0, 0.0)) -> trimesh.Trimesh:
    """A cylinder along z from `z_bottom` to `z_top`."""
    return frustum_z(radius, radius, z_bottom, z_top, center_xy)


def ring_points(center, axis, radius: float, sections: int = CIRCLE_SECTIONS) -> np.ndarray:
    """Points of a circle of `radius` around `center` in the plane normal to `axis`."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    # Any vector not parallel to the axis seeds the in-plane basis.
    seed = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, seed)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    c = circle(1.0, sections)
    return np.asarray(center, dtype=float) + radius * (np.outer(c[:, 0], u) + np.outer(c[:, 1], v))


def frustum_between(
    p0, p1, r0: float, r1: float, axis0=None, axis1=None, sections: int = CIRCLE_SECTIONS
) -> trimesh.Trimesh:
    """Convex hull of two circles: centre `p0`/`p1`, radius `r0`/`r1`.

    The circles lie in planes normal to `axis0`/`axis1` (default: the segment
    direction), which lets consecutive pieces of a curved object share a ring.
    """
    p0 = np.asarray(p0, dtype=float)
    p1 = np.asarray(p1, dtype=float)
    direction = p1 - p0
    axis0 = direction if axis0 is None else axis0
    axis1 = direction if axis1 is None else axis1
    return hull(np.vstack([ring_points(p0, axis0, r0, sections), ring_points(p1, axis1, r1, sections)]))


def ellipsoid(radii, center=(0.0, 0.0, 0.0), subdivisions: int = 2) -> trimesh.Trimesh:
    """An ellipsoid approximated by a scaled icosphere."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return hull(sphere.vertices * np.asarray(radii, dtype=float) + np.asarray(center, dtype=float))


# ----------------------------------------------------------------------------
# Whole-object helpers.


def bottom_center_offset(meshes: list[trimesh.Trimesh]) -> np.ndarray:
    """Translation that puts the bottom centre of the meshes' joint AABB at 0."""
    vertices = np.vstack([m.vertices for m in meshes])
    lo = vertices.min(axis=0)
    hi = vertices.max(axis=0)
    return -np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])


def extents_of(meshes: list[trimesh.Trimesh]) -> np.ndarray:
    """Size of the joint axis-aligned bounding box of `meshes`."""
    vertices = np.vstack([m.vertices for m in meshes])
    return vertices.max(axis=0) - vertices.min(axis=0)


def combine_mass_properties(
    items: list[tuple[trimesh.Trimesh, float]],
) -> MassProperties:
    """Mass properties of watertight meshes with the given densities.

    Pieces are summed, so overlapping pieces would count twice; the procedural
    builders keep pieces touching rather than overlapping.

    Args:
        items: (mesh, density_kg_m3) pairs; meshes must be watertight.

    Returns:
        The combined mass properties, inertia about the combined COM.
    """
    masses, centers, inertias, volume = [], [], [], 0.0
    for mesh, density in items:
        props = mesh.mass_properties  # computed at unit density
        vol = float(props.volume)
        if not vol > 0:
            raise ValueError(f"mesh piece has non-positive volume {vol}")
        volume += vol
        masses.append(density * vol)
        centers.append(np.asarray(props.center_mass, dtype=float))
        inertias.append(density * np.asarray(props.inertia, dtype=float))
    mass = float(sum(masses))
    com = sum(m * c for m, c in zip(masses, centers)) / mass
    inertia = np.zeros((3, 3))
    for m, c, inertia_i in zip(masses, centers, inertias):
        d = c - com
        # Parallel-axis theorem, tensor form.
        inertia += inertia_i + m * (d @ d * np.eye(3) - np.outer(d, d))
    inertia = 0.5 * (inertia + inertia.T)
    return MassProperties(mass, volume, com, inertia)


def union_mesh(meshes: list[trimesh.Trimesh], *, strict: bool = False) -> trimesh.Trimesh:
    """Boolean union of closed meshes (manifold3d), or their concatenation.

    The union has no internal faces, which keeps the visual mesh clean. If
    manifold3d rejects an input (it should not for convex hulls) the plain
    concatenation is returned (for rendering the two look the same), or a
    ValueError is raised if `strict`.
    """
    try:
        import manifold3d

        solids = []
        for mesh in meshes:
            solid = manifold3d.Manifold(
                manifold3d.Mesh64(
                    vert_properties=np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                    tri_verts=np.ascontiguousarray(mesh.faces, dtype=np.uint32),
                )
            )
            if solid.status() != manifold3d.Error.NoError or solid.is_empty():
                raise ValueError(f"manifold3d rejected a piece: {solid.status()}")
            solids.append(solid)
        result = manifold3d.Manifold.batch_boolean(solids, manifold3d.OpType.Add)
        out = result.to_mesh64()
        union = trimesh.Trimesh(
            vertices=np.asarray(out.vert_properties)[:, :3],
            faces=np.asarray(out.tri_verts, dtype=np.int64),
            process=False,
        )
        if len(union.faces) == 0:
            raise ValueError("empty union")
        return union
    except (ImportError, ValueError):
        if strict:
            raise ValueError("manifold3d could not unite the meshes") from None
        return trimesh.util.concatenate(meshes)


def obj_text(mesh: trimesh.Trimesh, *, face_normals: bool, header: str = "") -> str:
    """Deterministic Wavefront OBJ text for `mesh` (no material library).

    Args:
        mesh: The mesh to write.
        face_normals: Write one `vn` per face (flat shading; renderers need
            normals and faceted primitives should look faceted).
        header: A comment line to put on top.
    """
    lines = [f"# {header}"] if header else []
    vertices = np.asarray(mesh.vertices, dtype=float)
    faces = np.asarray(mesh.faces, dtype=np.int64) + 1
    # 1 micrometre resolution; fixed formatting keeps regenerated files identical.
    lines.extend(f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices)
    if face_normals:
        normals = np.asarray(mesh.face_normals, dtype=float)
        lines.extend(f"vn {x:.5f} {y:.5f} {z:.5f}" for x, y, z in normals)
        lines.extend(
            f"f {a}//{i} {b}//{i} {c}//{i}" for i, (a, b, c) in enumerate(faces, start=1)
        )
    else:
        lines.extend(f"f {a} {b} {c}" for a, b, c in faces)
    return "\n".join(lines) + "\n"


def write_obj(path: Path, mesh: trimesh.Trimesh, *, face_normals: bool, header: str = "") -> None:
    """Writes `mesh` to `path` as OBJ (see `obj_text`)."""
    Path(path).write_text(obj_text(mesh, face_normals=face_normals, header=header))
