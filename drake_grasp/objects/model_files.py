"""Writing one object directory: model.urdf, visual.obj, collision_XX.obj, meta.json.

The directory is assembled in a temporary folder next to the target and moved
into place with a single rename, so readers never see a half-written object.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import escape

import numpy as np

from drake_grasp.objects.geometry import MassProperties, write_obj

if TYPE_CHECKING:  # annotations only
    import trimesh

MODEL_FILE = "model.urdf"
META_FILE = "meta.json"
VISUAL_FILE = "visual.obj"
BODY_NAME = "body"


def collision_file(index: int) -> str:
    """File name of the `index`-th convex collision piece."""
    return f"collision_{index:02d}.obj"


@dataclass(frozen=True)
class ContactMaterial:
    """Drake proximity properties shared by all collision pieces of an object.

    Attributes:
        hydroelastic_modulus_pa: Compliant-hydroelastic modulus (Pa). This is
            not Young's modulus: it is the pressure at the deepest point of
            the convex piece's pressure field, so it sets the apparent
            stiffness of contact. ~1e6 feels like fruit, ~5e7 like ceramic.
        mu_static: Static Coulomb friction.
        mu_dynamic: Dynamic Coulomb friction (the only one discrete SAP uses).
        relaxation_time_s: Dissipation time scale used by Drake's discrete
            (SAP/lagged) contact solvers.
    """

    hydroelastic_modulus_pa: float
    mu_static: float
    mu_dynamic: float
    relaxation_time_s: float = 0.1


def check_mesh_references(model_path: Path, root) -> None:
    """Raises ValueError unless every mesh file a model refers to exists and is non-empty.

    Drake would otherwise stop the scene build with a parser error deep inside a trial.

    Args:
        model_path: The model.urdf (relative mesh names are resolved against its folder).
        root: Its parsed XML root element.
    """
    for mesh in root.iter("mesh"):
        filename = mesh.get("filename")
        if not filename:
            raise ValueError(f"{model_path}: a <mesh> element has no filename")
        if "://" in filename:  # package:// and file:// URIs are resolved by Drake's parser
            continue
        path = Path(model_path).parent / filename
        if not path.is_file():
            raise ValueError(f"{model_path}: refers to mesh {filename!r}, but {path} does not exist "
                             "(an incomplete object folder: re-import the object)")
        if path.stat().st_size == 0:
            raise ValueError(f"{model_path}: refers to mesh {filename!r}, but {path} is empty "
                             "(an incomplete object folder: re-import the object)")


def _fmt(value: float) -> str:
    return f"{float(value):.9g}"


def urdf_text(
    model_name: str,
    mass: MassProperties,
    num_collision: int,
    rgba: tuple[float, float, float, float],
    contact: ContactMaterial,
) -> str:
    """URDF text (with Drake's extensions) of a one-body model with convex compliant
    collisions. URDF rather than SDFormat: Drake parses it in well under a millisecond,
    against ~30 ms for the same model in SDFormat, and scenes are built per trial."""
    c = mass.com_m
    inertia = mass.inertia_kg_m2
    rgba_text = " ".join(_fmt(v) for v in rgba)
    proximity = (
        "      <drake:proximity_properties>\n"
        "        <drake:compliant_hydroelastic/>\n"
        f"        <drake:hydroelastic_modulus value=\"{_fmt(contact.hydroelastic_modulus_pa)}\"/>\n"
        f"        <drake:relaxation_time value=\"{_fmt(contact.relaxation_time_s)}\"/>\n"
        f"        <drake:mu_static value=\"{_fmt(contact.mu_static)}\"/>\n"
        f"        <drake:mu_dynamic value=\"{_fmt(contact.mu_dynamic)}\"/>\n"
        "      </drake:proximity_properties>\n"
    )
    collisions = "".join(
        f'    <collision name="collision_{i:02d}">\n'
        f'      <geometry><mesh filename="{collision_file(i)}"><drake:declare_convex/></mesh></geometry>\n'
        f"{proximity}"
        "    </collision>\n"
        for i in range(num_collision)
    )
    return (
        '<?xml version="1.0"?>\n'
        f'<robot name="{escape(model_name)}" xmlns:drake="http://drake.mit.edu">\n'
        f'  <link name="{BODY_NAME}">\n'
        "    <inertial>\n"
        f'      <origin xyz="{_fmt(c[0])} {_fmt(c[1])} {_fmt(c[2])}" rpy="0 0 0"/>\n'
        f'      <mass value="{_fmt(mass.mass_kg)}"/>\n'
        f'      <inertia ixx="{_fmt(inertia[0, 0])}" ixy="{_fmt(inertia[0, 1])}" '
        f'ixz="{_fmt(inertia[0, 2])}" iyy="{_fmt(inertia[1, 1])}" iyz="{_fmt(inertia[1, 2])}" '
        f'izz="{_fmt(inertia[2, 2])}"/>\n'
        "    </inertial>\n"
        '    <visual name="visual">\n'
        f'      <geometry><mesh filename="{VISUAL_FILE}"/></geometry>\n'
        f'      <material name="{escape(model_name)}_color"><color rgba="{rgba_text}"/></material>\n'
        "    </visual>\n"
        f"{collisions}"
        "  </link>\n"
        "</robot>\n"
    )


def write_object_dir(
    target: Path,
    *,
    model_name: str,
    visual: trimesh.Trimesh,
    collision: list[trimesh.Trimesh],
    mass: MassProperties,
    rgba: tuple[float, float, float, float],
    contact: ContactMaterial,
    meta: dict,
    overwrite: bool = False,
) -> bool:
    """Writes a complete object directory at `target`, atomically.

    Args:
        target: The object directory to create (its parent is created).
        model_name: model name (the object id).
        visual: Visual mesh in the object frame.
        collision: Convex collision pieces in the object frame.
        mass: Mass properties written to `<inertial>`.
        rgba: Diffuse colour of the visual.
        contact: Proximity properties of every collision piece.
        meta: Content of meta.json (written as given, keys sorted).
        overwrite: Replace an existing `target`. Without it an existing target
            is kept (another process finished first) and False is returned.

    Returns:
        True if this call put the directory in place, False if an existing one
        was kept.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{target.name}-", dir=target.parent))
    try:
        write_obj(tmp / VISUAL_FILE, visual, face_normals=True, header=f"{model_name} visual")
        for i, piece in enumerate(collision):
            header = f"{model_name} convex piece {i}"
            write_obj(tmp / collision_file(i), piece, face_normals=False, header=header)
        (tmp / MODEL_FILE).write_text(urdf_text(model_name, mass, len(collision), rgba, contact))
        (tmp / META_FILE).write_text(json.dumps(_jsonable(meta), indent=2, sort_keys=True) + "\n")
        os.chmod(tmp, 0o755)  # mkdtemp makes it 0700; the library may be shared.
        if overwrite and target.exists():
            return _replace_existing(tmp, target)
        try:
            os.rename(tmp, target)
        except OSError:
            if target.is_dir():  # another process (or an earlier call) won the race
                return False
            raise
        return True
    except OSError as e:
        if e.filename is not None:
            raise
        message = f"cannot write object folder {target}: {e.strerror or e}"  # e.g. a full disk
        raise (OSError(e.errno, message) if e.errno else OSError(message)) from e
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _replace_existing(tmp: Path, target: Path) -> bool:
    # Move the old one aside first so the target name is never half-filled.
    trash = Path(tempfile.mkdtemp(prefix=f".old-{target.name}-", dir=target.parent))
    old = trash / "old"
    os.rename(target, old)
    try:
        os.rename(tmp, target)
    except OSError:
        os.rename(old, target)
        raise
    finally:
        shutil.rmtree(trash, ignore_errors=True)
    return True


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(f"{float(value):.9g}")
    if isinstance(value, (np.integer,)):
        return int(value)
    return value
