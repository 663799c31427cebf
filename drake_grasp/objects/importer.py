"""Importing a user mesh (OBJ/STL/PLY/glTF/GLB) as a graspable object.

The result has the same folder layout as the procedural objects: the repaired
mesh as the visual, a CoACD convex decomposition as compliant-hydroelastic
`Convex` collision pieces, and mass properties from the mesh and a density.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from drake_grasp.core.lazy import lazy_import

from drake_grasp.objects import categories as cat
from drake_grasp.objects import geometry as g
from drake_grasp.objects.library import ObjectInfo
from drake_grasp.objects.model_files import ContactMaterial, write_object_dir

trimesh = lazy_import("trimesh")  # loaded when first used

SUPPORTED_SUFFIXES = (".obj", ".stl", ".ply", ".gltf", ".glb")
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_-]{1,100}$")
# Plausible size of a graspable household object: its bounding-box diagonal (a 1 cm
# bead to a 1 m broom handle) and its thinnest side (a sheet thinner than 1 mm has no
# volume to simulate as a compliant solid).
MIN_DIAGONAL_M = 0.01
MAX_DIAGONAL_M = 1.0
MIN_THICKNESS_M = 0.001
# Faces kept for the object's mesh: ample for a 64x64 depth image at grasping distance;
# larger meshes are simplified first (CoACD on 200k faces took minutes and GBs).
MAX_FACES = 20_000
# Larger files are refused rather than simplified (loading alone takes long).
MAX_INPUT_FACES = 2_000_000
USER_RGBA = (0.7, 0.7, 0.72, 1.0)
# The file's up axis -> the rotation that makes it z (the world's up here, as in Drake).
# glTF is y-up by specification; Drake's own glTF loading turns +y to +z the same way.
UP_AXIS_ROTATIONS = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),  # R_x(+90 deg)
}
Y_UP_SUFFIXES = (".gltf", ".glb")


def _mass_of(path: Path, mesh, watertight: bool, density_kg_m3: float,
             warnings: list[str]) -> tuple:
    """(mass properties, what the volume was taken from) of the imported mesh: the
    repaired mesh, or its convex hull where it could not be made watertight (with a
    warning, as for an unusual mass). ValueError where it encloses no volume."""
    if watertight:
        solid = mesh
        volume_basis = "repaired mesh"
    else:
        solid = mesh.convex_hull
        volume_basis = "convex hull (the mesh could not be made watertight)"
        warnings.append(
            "mesh is not watertight after repair; mass and inertia use its convex hull, "
            "which overestimates the volume of concave shapes"
        )
    props = solid.mass_properties
    mass = g.MassProperties(
        mass_kg=density_kg_m3 * float(props.volume),
        volume_m3=float(props.volume),
        com_m=np.asarray(props.center_mass, dtype=float),
        inertia_kg_m2=density_kg_m3 * np.asarray(props.inertia, dtype=float),
    )
    if not (math.isfinite(mass.mass_kg) and mass.mass_kg > 0):
        raise ValueError(f"mesh file {path}: encloses no volume (mass {mass.mass_kg!r} kg); "
                         "expected a closed solid")
    if not 0.01 <= mass.mass_kg <= 2.0:
        warnings.append(
            f"mass {mass.mass_kg:.4g} kg is unusual for a graspable object; check scale and density"
        )
    return mass, volume_basis


def import_mesh(
    mesh_path: str | Path,
    *,
    name: str,
    library_dir: str | Path,
    scale: float = 1.0,
    category: str = "user",
    split: str = "test",
    density_kg_m3: float = 500.0,
    max_convex_hulls: int = 12,
    seed: int = 0,
    overwrite: bool = False,
    hydroelastic_modulus_pa: float = 1e7,
    up_axis: str | None = None,
) -> ObjectInfo:
    """Imports a mesh file into `library_dir/<name>/`.

    The mesh is turned so that the file's up axis (`up_axis`) becomes z, and
    translated so the bottom centre of its bounding box is the origin.

    Args:
        mesh_path: OBJ, STL, PLY, glTF or GLB file (a glTF scene's meshes are
            concatenated with their node transforms).
        name: Object id and folder name: letters, digits, '_' and '-'.
        library_dir: Library folder (created if needed).
        scale: Factor from file units to metres (0.001 for millimetres).
        category: Category label (same character set as `name`).
        split: "train" or "test".
        density_kg_m3: Density used for the mass (volume of the repaired mesh,
            or of its convex hull if it cannot be made watertight).
        max_convex_hulls: Upper bound on CoACD collision pieces.
        seed: CoACD seed (the decomposition is deterministic given it).
        overwrite: Replace an existing object of that name.
        hydroelastic_modulus_pa: Compliant-hydroelastic modulus of the pieces.
        up_axis: The file's up axis, "z" or "y" (turned to z by +90 degrees about
            x). None: "y" for glTF/GLB (their specification's, as Drake reads
            them), "z" for OBJ, STL and PLY.

    Returns:
        The new object's info.

    Raises:
        FileNotFoundError: `mesh_path` does not exist.
        FileExistsError: The object exists and `overwrite` is False.
        ValueError: Bad argument, unreadable/empty mesh, only degenerate faces, a
            flat mesh (no volume), more than `MAX_INPUT_FACES` faces, or an
            implausible size (the message names the file and suggests a `--scale`).

    Meshes with more than `MAX_FACES` faces are simplified first (a warning in
    meta.json says from how many faces to how many).
    """
    path = Path(mesh_path).expanduser()
    _check_args(name, category, split, scale, density_kg_m3, max_convex_hulls, seed,
                hydroelastic_modulus_pa)
    up_axis = _up_axis_of(path, up_axis)
    target = Path(library_dir).expanduser() / name
    if target.exists() and not overwrite:
        raise FileExistsError(
            f"object {name!r} already exists at {target}; pass --overwrite (overwrite=True) to replace it"
        )

    geometries = _load(path)
    for geometry in geometries:
        geometry.apply_scale(scale)
        geometry.apply_transform(_up_turn(up_axis))
    _check_size(path, geometries, scale)
    warnings: list[str] = []
    mesh, watertight = _repair_all(path, geometries, warnings)
    if len(mesh.faces) > MAX_FACES:
        mesh, watertight = _simplify(mesh, watertight, warnings)
    _check_solid(path, mesh)
    mesh.apply_translation(g.bottom_center_offset([mesh]))

    mass, volume_basis = _mass_of(path, mesh, watertight, density_kg_m3, warnings)
    pieces = _decompose(mesh, watertight, max_convex_hulls, seed, warnings)
    contact = ContactMaterial(hydroelastic_modulus_pa, mu_static=0.6, mu_dynamic=0.5)
    meta = {
        "id": name, "category": category, "split": split,
        "source": path.name, "source_path": str(path.resolve()),
        "generator_version": cat.GENERATOR_VERSION,
        "scale": scale, "up_axis": up_axis, "density_kg_m3": density_kg_m3,
        "mass_kg": mass.mass_kg, "extents_m": g.extents_of([mesh]),
        "volume_m3": mass.volume_m3, "volume_basis": volume_basis, "com_m": mass.com_m,
        "num_collision_pieces": len(pieces),
        "coacd": {"max_convex_hulls": max_convex_hulls, "seed": seed},
        "rgba": USER_RGBA,
        "hydroelastic_modulus_pa": contact.hydroelastic_modulus_pa,
        "mu_static": contact.mu_static, "mu_dynamic": contact.mu_dynamic,
        "relaxation_time_s": contact.relaxation_time_s,
        "warnings": warnings,
    }
    placed = write_object_dir(target, model_name=name, visual=mesh, collision=pieces, mass=mass,
                              rgba=USER_RGBA, contact=contact, meta=meta, overwrite=overwrite)
    if not placed:
        raise FileExistsError(f"object {name!r} was created at {target} by someone else "
                              "meanwhile; not replaced")
    return ObjectInfo.from_dir(target)


def _up_axis_of(path: Path, up_axis: str | None) -> str:
    """The file's up axis: `up_axis`, or by default "y" for glTF/GLB and "z" otherwise."""
    if up_axis is None:
        return "y" if path.suffix.lower() in Y_UP_SUFFIXES else "z"
    if up_axis not in UP_AXIS_ROTATIONS:
        raise ValueError(f"up_axis {up_axis!r} is not one of {list(UP_AXIS_ROTATIONS)}")
    return up_axis


def _up_turn(up_axis: str) -> np.ndarray:
    """The 4x4 transform that turns `up_axis` to z."""
    turn = np.eye(4)
    turn[:3, :3] = UP_AXIS_ROTATIONS[up_axis]
    return turn


def _check_args(name, category, split, scale, density, max_hulls, seed, modulus) -> None:
    if not isinstance(name, str) or not NAME_PATTERN.match(name):
        raise ValueError(f"object name {name!r} is invalid; use 1-100 letters, digits, '_' or '-'")
    if not isinstance(category, str) or not NAME_PATTERN.match(category):
        raise ValueError(f"category {category!r} is invalid; use 1-100 letters, digits, '_' or '-'")
    if split not in cat.SPLITS:
        raise ValueError(f"split {split!r} is not one of {list(cat.SPLITS)}")
    positive = (("scale", scale), ("density_kg_m3", density), ("hydroelastic_modulus_pa", modulus))
    for label, value in positive:
        is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not is_number or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{label} must be a positive finite number, got {value!r}")
    if isinstance(max_hulls, bool) or not isinstance(max_hulls, (int, np.integer)) or max_hulls < 1:
        raise ValueError(f"max_convex_hulls must be an integer >= 1, got {max_hulls!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")


def _load(path: Path) -> list[trimesh.Trimesh]:
    """The file's triangle meshes, each with its scene transform applied."""
    if not path.is_file():
        raise FileNotFoundError(f"mesh file {path} does not exist (or is not a file)")
    suffix = path.suffix.lower()
    kind = suffix[1:].upper()
    if suffix not in SUPPORTED_SUFFIXES:
        raise ValueError(
            f"mesh file {path}: unsupported type {suffix!r}; expected one of {list(SUPPORTED_SUFFIXES)}"
        )
    try:
        # process=False: trimesh would otherwise drop NaN vertices silently.
        scene = trimesh.load_scene(str(path), process=False)
    except Exception as exc:  # trimesh raises many types on garbage input
        # (An ImportError here is trimesh's text-encoding sniffing for garbage bytes.)
        detail = "" if isinstance(exc, ImportError) else f": {type(exc).__name__}: {exc}"
        raise ValueError(f"mesh file {path}: cannot be read, not a valid {kind} file{detail}") from exc
    meshes = []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geometry = scene.geometry.get(name)
        if not isinstance(geometry, trimesh.Trimesh) or len(geometry.faces) == 0:
            continue  # point clouds, paths, empty meshes
        vertices = trimesh.transform_points(np.asarray(geometry.vertices, dtype=float), transform)
        if not np.all(np.isfinite(vertices)):
            raise ValueError(f"mesh file {path}: has non-finite vertex coordinates")
        faces = np.asarray(geometry.faces)
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"mesh file {path}: a face refers to vertex {int(faces.max()) + 1}, "
                             f"but there are only {len(vertices)} vertices")
        meshes.append(trimesh.Trimesh(vertices=vertices, faces=faces, process=False))
    if not meshes:
        raise ValueError(f"mesh file {path}: contains no triangles (empty, or not a valid {kind} file)")
    num_faces = sum(len(m.faces) for m in meshes)
    if num_faces > MAX_INPUT_FACES:
        raise ValueError(
            f"mesh file {path}: has {num_faces} faces, more than the {MAX_INPUT_FACES} accepted; "
            f"simplify it first (meshes above {MAX_FACES} faces are simplified on import)"
        )
    return meshes


def _check_size(path: Path, meshes: list[trimesh.Trimesh], scale: float) -> None:
    diagonal = float(np.linalg.norm(g.extents_of(meshes)))
    if MIN_DIAGONAL_M <= diagonal <= MAX_DIAGONAL_M:
        return
    # A power of ten that brings the object to ~20 cm, the size of a typical household item.
    suggestion = scale * 10.0 ** round(math.log10(0.2 / diagonal)) if diagonal > 0 else None
    hint = f"--scale {suggestion:g}" if suggestion else "a --scale"
    ratio = round(suggestion / scale, 9) if suggestion else None
    if ratio == 1e-3:
        hint += " (the file looks like millimetres)"
    elif ratio == 1e-2:
        hint += " (the file looks like centimetres)"
    elif diagonal > MAX_DIAGONAL_M:
        hint += "; a mesh in millimetres needs --scale 0.001"
    raise ValueError(
        f"mesh file {path}: bounding-box diagonal is {diagonal:.4g} m after scale {scale:g}, outside the "
        f"plausible range [{MIN_DIAGONAL_M}, {MAX_DIAGONAL_M}] m for a graspable object; "
        f"try {hint}"
    )


def _check_solid(path: Path, mesh: trimesh.Trimesh) -> None:
    """Refuses a flat mesh (a single triangle, a sheet, collinear points): no volume."""
    thickness = 0.0
    try:
        with np.errstate(divide="ignore", invalid="ignore"):  # a flat hull: volume 0
            hull = trimesh.convex.convex_hull(np.asarray(mesh.vertices, dtype=float))
            if hull.volume > 0:
                thickness = float(min(hull.bounding_box_oriented.primitive.extents))
    except Exception:  # qhull: fewer than 4 points, or all in a plane
        thickness = 0.0
    if thickness < MIN_THICKNESS_M:
        extents = " x ".join(f"{e:.3g}" for e in mesh.extents)
        raise ValueError(
            f"mesh file {path}: is flat (thinnest side {thickness * 1000:.3g} mm, bounding box "
            f"{extents} m; a graspable object must be at least {MIN_THICKNESS_M * 1000:g} mm thick): "
            f"a single triangle or an open sheet has no volume to simulate"
        )


def _repair(mesh: trimesh.Trimesh, warnings: list[str]) -> trimesh.Trimesh:
    """Merges vertices, drops degenerate/duplicate faces, fills holes, fixes normals."""
    mesh.merge_vertices()
    before = len(mesh.faces)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if 0 < len(mesh.faces) < before:
        warnings.append(f"dropped {before - len(mesh.faces)} degenerate (zero-area) or duplicate faces")
    if len(mesh.faces) and not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
        if mesh.is_watertight:
            warnings.append("filled holes to make the mesh watertight")
    if len(mesh.faces):
        with np.errstate(divide="ignore", invalid="ignore"):  # a flat shell has volume 0
            trimesh.repair.fix_normals(mesh)  # consistent winding, outward normals
    return mesh


def _repair_all(
    path: Path, meshes: list[trimesh.Trimesh], warnings: list[str]
) -> tuple[trimesh.Trimesh, bool]:
    """One cleaned mesh from the file's meshes, and whether it is a watertight solid.

    Each mesh is repaired on its own (merging vertices across separate shells
    would make touching shells non-manifold); watertight shells are then
    united with manifold3d so overlaps are not counted twice.
    """
    repaired = [_repair(m, warnings) for m in meshes]
    repaired = [m for m in repaired if len(m.faces)]
    if not repaired:
        raise ValueError(f"mesh file {path}: has only degenerate (zero-area or duplicate) faces")
    with np.errstate(divide="ignore", invalid="ignore"):  # a flat closed shell: volume 0
        closed = [bool(m.is_watertight and m.volume > 0) for m in repaired]
    if all(closed):
        if len(repaired) == 1:
            return repaired[0], True
        try:
            union = g.union_mesh(repaired, strict=True)
            if union.is_watertight and union.volume > 0:
                return union, True
        except ValueError:
            pass
    if any(closed) and not all(closed):
        warnings.append(f"{closed.count(False)} of {len(closed)} mesh parts are open surfaces")
    mesh = trimesh.util.concatenate(repaired) if len(repaired) > 1 else repaired[0]
    return mesh, False


def _simplify(
    mesh: trimesh.Trimesh, watertight: bool, warnings: list[str]
) -> tuple[trimesh.Trimesh, bool]:
    """At most `MAX_FACES` faces: manifold3d's simplification for a closed solid (it stays
    closed), vertex clustering on a grid for an open surface. Coarser tolerances are
    tried until the budget is met."""
    before = len(mesh.faces)
    diagonal = float(np.linalg.norm(mesh.extents))
    out = mesh
    for fraction in (1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2):
        tolerance = fraction * diagonal
        out = _simplify_solid(mesh, tolerance) if watertight else None
        if out is None:  # open surface, or manifold3d refused the mesh
            out = _cluster_vertices(mesh, tolerance)
        if 0 < len(out.faces) <= MAX_FACES:
            break
    closed = bool(watertight and out.is_watertight and out.volume > 0)
    warnings.append(
        f"simplified from {before} to {len(out.faces)} faces (tolerance {tolerance * 1000:.2g} mm)"
    )
    return out, closed


def _simplify_solid(mesh: trimesh.Trimesh, tolerance: float) -> "trimesh.Trimesh | None":
    import manifold3d

    solid = manifold3d.Manifold(manifold3d.Mesh64(
        vert_properties=np.ascontiguousarray(mesh.vertices, dtype=np.float64),
        tri_verts=np.ascontiguousarray(mesh.faces, dtype=np.uint32)))
    if solid.status() != manifold3d.Error.NoError or solid.is_empty():
        return None
    out = solid.simplify(tolerance).to_mesh64()
    result = trimesh.Trimesh(np.asarray(out.vert_properties)[:, :3],
                             np.asarray(out.tri_verts, dtype=np.int64), process=False)
    if len(result.faces) == 0 or not result.is_watertight:
        return None
    trimesh.repair.fix_normals(result)
    return result


def _cluster_vertices(mesh: trimesh.Trimesh, cell: float) -> trimesh.Trimesh:
    """Merges the vertices in each grid cell of size `cell` into their mean."""
    vertices = np.asarray(mesh.vertices, dtype=float)
    keys = np.floor((vertices - vertices.min(axis=0)) / cell).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse)
    merged = np.zeros((len(counts), 3))
    np.add.at(merged, inverse, vertices)
    merged /= counts[:, None]
    out = trimesh.Trimesh(merged, inverse[np.asarray(mesh.faces)], process=False)
    out.update_faces(out.nondegenerate_faces())
    out.update_faces(out.unique_faces())
    out.remove_unreferenced_vertices()
    return out


def _decompose(
    mesh: trimesh.Trimesh, watertight: bool, max_hulls: int, seed: int, warnings: list[str]
) -> list[trimesh.Trimesh]:
    """Convex collision pieces: the hull itself for convex meshes, else CoACD."""
    if watertight and mesh.is_convex:
        return [g.hull(mesh.vertices)]
    import coacd

    coacd.set_log_level("error")
    # CoACD's "auto" preprocessing remeshes non-manifold input itself.
    raw = coacd.run_coacd(
        coacd.Mesh(np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)),
        max_convex_hull=int(max_hulls),
        seed=int(seed),
    )
    pieces = []
    for vertices, _faces in raw:
        try:
            pieces.append(g.hull(np.asarray(vertices, dtype=float)))
        except Exception:  # a flat sliver: qhull fails or the volume is zero
            continue
    if not pieces:
        warnings.append("convex decomposition failed; using the convex hull as the only collision piece")
        pieces = [g.hull(mesh.vertices)]
    return pieces
