"""Procedural household objects: 10 categories, 381 instances, fixed split.

Stands in for the 3DNet subset used by Viereck et al. (CoRL 2017): 381 objects
in 10 categories, split by instance into 331 train / 50 test. Each category
has a parameter sampler with dimension ranges taken from typical real objects
(cited per category below) and a builder that turns parameters into a handful
(<= 12) of convex parts.

Conventions shared by all builders:
  * metres, z up, the canonical "upright" pose is the object's natural resting
    pose on a table (bottle standing, hammer and banana lying on their side,
    toy car on its wheels);
  * after building, the parts are shifted so the origin is the centre of the
    bottom face of their joint axis-aligned bounding box (z=0 is the table);
  * parts touch rather than overlap (a few deliberate sub-millimetre overlaps
    make joints robust and are < 1 % of the volume), so the mass, computed as
    the sum over parts of density * volume, equals density * union volume;
  * every instance has a horizontal extent <= 75 mm in its canonical pose, so
    an 85 mm parallel-jaw gripper can close on it from above.

Instance `index` of a category draws its parameters from
`np.random.default_rng([spec.seed, index])`, so an id always maps to the same
geometry, independent of which other objects were generated.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from drake_grasp.objects import geometry as g
from drake_grasp.objects.geometry import MassProperties, Part
from drake_grasp.objects.model_files import ContactMaterial
from drake_grasp.objects.shapes import SHAPES, Params

# Bump whenever the geometry, masses or file contents of procedural objects
# change: the cache folder is named after it, so stale files are never reused.
GENERATOR_VERSION = 2

# The first NUM_TEST_PER_CATEGORY indices of every category are the test split.
NUM_TEST_PER_CATEGORY = 5
SPLITS = ("train", "test")


@dataclass(frozen=True)
class CategorySpec:
    """How to sample and build one category.

    Attributes:
        name: Category name (also the id prefix).
        seed: Fixed per-category seed; never derived from Python's salted hash().
        count: Number of instances.
        density_kg_m3: Default density of the parts (per-part overrides exist,
            e.g. a hammer's steel head).
        rgba: Diffuse colour of the visual.
        contact: Proximity properties of the collision pieces.
        sample: Draws a parameter dict from a seeded Generator.
        build: Turns (params, density) into convex parts.
    """

    name: str
    seed: int
    count: int
    density_kg_m3: float
    rgba: tuple[float, float, float, float]
    contact: ContactMaterial
    sample: Callable[[np.random.Generator], Params]
    build: Callable[[Params, float], list[Part]]



# ----------------------------------------------------------------------------
# The table. Densities are effective (whole-object mass / solid envelope
# volume) where the real object is hollow or partly filled. Hydroelastic
# moduli follow the material: ceramic/steel 5e7 Pa, aluminium 3e7, rigid
# plastic 2e7, thin PET 1e7, cardboard 5e6, fruit 1e6-2e6.

# name, seed, count, density kg/m^3, rgba, (modulus Pa, mu_static, mu_dynamic)
_TABLE = [
    # Real hollow geometry, so the true material density: stoneware 2.3 g/cm^3.
    ("mug", 1101, 39, 2300.0, (0.25, 0.45, 0.80, 1.0), (5e7, 0.5, 0.4)),
    # Handle: hickory ~750 kg/m^3; head parts use steel (7850) per part.
    ("hammer", 1102, 38, 750.0, (0.55, 0.40, 0.25, 1.0), (5e7, 0.6, 0.5)),
    # ~30 % full PET bottle: 25 g plastic + water, over the closed envelope.
    ("bottle", 1103, 38, 300.0, (0.55, 0.80, 0.90, 1.0), (1e7, 0.5, 0.4)),
    # ~40 % full carton (full would be ~1030 kg/m^3, too heavy for 1 L sizes).
    ("tetra_pak", 1104, 38, 400.0, (0.95, 0.90, 0.60, 1.0), (5e6, 0.6, 0.5)),
    # Aluminium/plastic shell with batteries inside.
    ("flashlight", 1105, 38, 900.0, (0.20, 0.20, 0.22, 1.0), (3e7, 0.5, 0.4)),
    # Electronics in a plastic/metal shell: a 0.3 kg compact of ~0.4 L.
    ("camera", 1106, 38, 750.0, (0.12, 0.12, 0.12, 1.0), (2e7, 0.6, 0.5)),
    # Full can: 0.39 kg over a 0.42 L envelope is ~930; 800 allows for head space.
    ("can", 1107, 38, 800.0, (0.80, 0.15, 0.15, 1.0), (3e7, 0.5, 0.4)),
    ("apple", 1108, 38, 830.0, (0.55, 0.75, 0.20, 1.0), (2e6, 0.6, 0.5)),
    # Toy cars are partly hollow plastic, partly die-cast zinc.
    ("toy_car", 1109, 38, 700.0, (0.95, 0.60, 0.05, 1.0), (2e7, 0.55, 0.45)),
    ("banana", 1110, 38, 950.0, (0.95, 0.85, 0.20, 1.0), (1e6, 0.6, 0.5)),
]
CATEGORY_SPECS: dict[str, CategorySpec] = {
    name: CategorySpec(
        name, seed, count, density, rgba, ContactMaterial(modulus, mu_s, mu_d), *SHAPES[name]
    )
    for name, seed, count, density, rgba, (modulus, mu_s, mu_d) in _TABLE
}
CATEGORIES: tuple[str, ...] = tuple(sorted(CATEGORY_SPECS))
# The label of a grasp whose pads touch no single object (none, or two different ones)
# where grasps are counted by the category of their object.
NO_SINGLE_OBJECT = "(no single object)"


def object_id(category: str, index: int) -> str:
    """The id of instance `index` of `category`, e.g. `mug_003`."""
    return f"{category}_{index:03d}"


def split_of(index: int) -> str:
    """Split of instance `index` of any category (first indices are test)."""
    return "test" if index < NUM_TEST_PER_CATEGORY else "train"


def builtin_ids() -> list[str]:
    """All procedural object ids, sorted."""
    return sorted(object_id(name, i) for name, spec in CATEGORY_SPECS.items() for i in range(spec.count))


def parse_object_id(oid: str) -> tuple[CategorySpec, int]:
    """(category spec, index) of a procedural id; ValueError if it is not one."""
    category, sep, index_text = oid.rpartition("_")
    spec = CATEGORY_SPECS.get(category)
    if not sep or spec is None or not index_text.isdigit() or len(index_text) != 3:
        raise ValueError(
            f"{oid!r} is not a procedural object id; expected '<category>_<NNN>' with category in "
            f"{list(CATEGORIES)}, e.g. 'mug_000'"
        )
    index = int(index_text)
    if index >= spec.count:
        raise ValueError(f"{oid!r}: category {category!r} has indices 000-{spec.count - 1:03d}")
    return spec, index


@dataclass(frozen=True)
class GeneratedObject:
    """A procedural object in memory, in its canonical frame.

    Attributes:
        id: Object id.
        category: Category name.
        index: Instance index within the category.
        split: "train" or "test".
        params: The sampled parameters (metres / radians / flags).
        parts: Convex parts, shifted so the AABB bottom centre is the origin.
        mass: Mass properties of the parts.
        extents_m: AABB size in the canonical pose.
    """

    id: str
    category: str
    index: int
    split: str
    params: Params
    parts: list[Part]
    mass: MassProperties
    extents_m: np.ndarray


def generate_object(oid: str) -> GeneratedObject:
    """Builds procedural object `oid` in memory (deterministic in `oid`)."""
    spec, index = parse_object_id(oid)
    rng = np.random.default_rng([spec.seed, index])
    params = spec.sample(rng)
    parts = spec.build(params, spec.density_kg_m3)
    offset = g.bottom_center_offset([part.mesh for part in parts])
    shifted = []
    for part in parts:
        mesh = part.mesh.copy()
        mesh.apply_translation(offset)
        shifted.append(Part(part.name, mesh, part.density_kg_m3))
    mass = g.combine_mass_properties([(part.mesh, part.density_kg_m3) for part in shifted])
    extents = g.extents_of([part.mesh for part in shifted])
    return GeneratedObject(oid, spec.name, index, split_of(index), params, shifted, mass, extents)
