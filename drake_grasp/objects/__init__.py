"""Graspable household objects for the simulation.

Two sources, one on-disk layout (`<library>/<object_id>/model.urdf`, ...):

* the built-in procedural library: 381 objects in 10 categories (mug, hammer,
  bottle, tetra_pak, flashlight, camera, can, apple, toy_car, banana), split
  by instance into 331 train / 50 test like the 3DNet subset of Viereck et
  al. (CoRL 2017); files are generated on first use into
  `$DRAKE_GRASP_CACHE` (default `~/.cache/drake_grasp`) `/objects-v<N>/`;
* user meshes imported with `import_mesh` into a folder read by
  `ObjectLibrary.from_dir`.

Typical use::

    lib = load_library(None)               # or load_library("my_objects/")
    info = lib.get(lib.ids(split="test")[0])
    Parser(plant).AddModels(str(info.model_path))   # body frame name: "body"
"""

from drake_grasp.objects.categories import (
    CATEGORIES,
    CATEGORY_SPECS,
    GENERATOR_VERSION,
    NUM_TEST_PER_CATEGORY,
    SPLITS,
    CategorySpec,
    GeneratedObject,
    builtin_ids,
    generate_object,
)
from drake_grasp.objects.importer import import_mesh
from drake_grasp.objects.library import (
    CACHE_ENV,
    ObjectInfo,
    ObjectLibrary,
    UnknownObjectError,
    builtin_library_dir,
    default_cache_root,
    load_library,
    visual_mesh,
    write_procedural_object,
)
from drake_grasp.objects.model_files import BODY_NAME

__all__ = [
    "BODY_NAME",
    "CACHE_ENV",
    "CATEGORIES",
    "CATEGORY_SPECS",
    "GENERATOR_VERSION",
    "NUM_TEST_PER_CATEGORY",
    "SPLITS",
    "CategorySpec",
    "GeneratedObject",
    "ObjectInfo",
    "ObjectLibrary",
    "UnknownObjectError",
    "visual_mesh",
    "builtin_ids",
    "builtin_library_dir",
    "default_cache_root",
    "generate_object",
    "import_mesh",
    "load_library",
    "write_procedural_object",
]
