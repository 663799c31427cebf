"""Object libraries: the built-in procedural set (cached on disk) and user folders.

An object on disk is a folder `<library>/<object_id>/` holding `model.urdf`
(one model named after the id, one body named `body`), `visual.obj`,
`collision_XX.obj` (one convex piece each) and `meta.json`.
"""

from __future__ import annotations

import hashlib
import json
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from drake_grasp.objects import categories as cat
from drake_grasp.objects.geometry import union_mesh
from drake_grasp.objects.model_files import (
    META_FILE,
    MODEL_FILE,
    VISUAL_FILE,
    check_mesh_references,
    write_object_dir,
)

CACHE_ENV = "DRAKE_GRASP_CACHE"


class UnknownObjectError(KeyError):
    """An object id that the library does not hold."""

    def __str__(self) -> str:  # KeyError would print the message in quotes
        return str(self.args[0]) if self.args else ""


@dataclass(frozen=True)
class ObjectInfo:
    """What a simulation needs to know about one object on disk.

    Attributes:
        id: Object id (also the model name and the folder name).
        category: Category name ("mug", ..., or "user" for imports).
        split: "train" or "test".
        mass_kg: Mass written in the model file.
        extents_m: Bounding-box size (x, y, z) in the canonical pose; the
            model frame origin is the bottom centre of that box.
        model_path: The model.urdf to give to Drake's Parser.
        directory: The object's folder.
    """

    id: str
    category: str
    split: str
    mass_kg: float
    extents_m: tuple[float, float, float]
    model_path: Path
    directory: Path

    @classmethod
    def from_dir(cls, path: str | Path) -> "ObjectInfo":
        """Reads an object folder, checking meta.json and model.urdf.

        Raises:
            ValueError: The folder is not a complete object (the message names
                the file and what is wrong).
        """
        directory = Path(path)
        meta_path = directory / META_FILE
        model_path = directory / MODEL_FILE
        if not meta_path.is_file():
            raise ValueError(f"{directory}: not an object folder, {META_FILE} is missing")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{meta_path}: unreadable JSON ({exc})") from exc
        if not isinstance(meta, dict):
            raise ValueError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")

        def field(key: str, kind: type, check=None, expected: str = ""):
            if key not in meta:
                raise ValueError(f"{meta_path}: missing key {key!r}")
            value = meta[key]
            ok = isinstance(value, kind) and not isinstance(value, bool)
            if ok and check is not None:
                ok = check(value)
            if not ok:
                expected_text = expected or kind.__name__
                raise ValueError(f"{meta_path}: key {key!r} has value {value!r}; expected {expected_text}")
            return value

        oid = field("id", str)
        if oid != directory.name:
            raise ValueError(
                f"{meta_path}: id {oid!r} does not match the folder name {directory.name!r} "
                "(object folders must be named after their id)"
            )
        category = field("category", str, lambda v: v != "", "a non-empty string")
        split = field("split", str, lambda v: v in cat.SPLITS, f"one of {list(cat.SPLITS)}")
        mass = field("mass_kg", (int, float), lambda v: v > 0, "a positive number")
        extents = field(
            "extents_m",
            list,
            lambda v: len(v) == 3 and all(isinstance(x, (int, float)) and x > 0 for x in v),
            "a list of 3 positive numbers",
        )
        _check_model(model_path, oid)
        extents_tuple = tuple(float(x) for x in extents)
        return cls(oid, category, split, float(mass), extents_tuple, model_path, directory)

    def read_meta(self) -> dict:
        """The full meta.json (parameters, volume, contact properties, ...)."""
        return json.loads((self.directory / META_FILE).read_text())


def _check_model(model_path: Path, oid: str) -> None:
    # A cheap structural check; Drake's parser does the real validation later.
    if not model_path.is_file():
        raise ValueError(f"{model_path}: missing ({MODEL_FILE} is required in every object folder)")
    try:
        root = ET.parse(model_path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ValueError(f"{model_path}: not well-formed XML ({exc})") from exc
    if root.tag != "robot":
        raise ValueError(f"{model_path}: expected a URDF <robot ...>, found <{root.tag}>")
    if root.get("name") != oid:
        raise ValueError(f"{model_path}: model name {root.get('name')!r}, expected the object id {oid!r}")
    check_mesh_references(model_path, root)


@lru_cache(maxsize=1024)
def _load_mesh(path: str, process: bool):
    import trimesh

    return trimesh.load(path, force="mesh", process=process)


def visual_mesh(info: ObjectInfo, *, process: bool = False):
    """The object's visual (surface) mesh in its own frame, read once per process.

    The mesh is shared between callers: treat it as read-only.
    """
    return _load_mesh(str(Path(info.directory) / VISUAL_FILE), bool(process))


def default_cache_root() -> Path:
    """`$DRAKE_GRASP_CACHE` if set (non-empty), else `~/.cache/drake_grasp`."""
    env = os.environ.get(CACHE_ENV, "").strip()
    return Path(env).expanduser() if env else Path.home() / ".cache" / "drake_grasp"


def builtin_library_dir(cache_dir: str | Path | None = None) -> Path:
    """Folder of the procedural objects: `<cache root>/objects-v<GENERATOR_VERSION>`."""
    root = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_root()
    return root / f"objects-v{cat.GENERATOR_VERSION}"


def write_procedural_object(oid: str, directory: Path) -> None:
    """Generates procedural object `oid` and writes it to `directory` atomically.

    If another process finished the same folder first, its copy is kept.
    """
    obj = cat.generate_object(oid)
    spec = cat.CATEGORY_SPECS[obj.category]
    meshes = [part.mesh for part in obj.parts]
    meta = {
        "id": obj.id,
        "category": obj.category,
        "split": obj.split,
        "index": obj.index,
        "source": "procedural",
        "generator_version": cat.GENERATOR_VERSION,
        "mass_kg": obj.mass.mass_kg,
        "extents_m": obj.extents_m,
        "volume_m3": obj.mass.volume_m3,
        "volume_basis": "sum of the convex parts' volumes (parts touch, they do not overlap)",
        "com_m": obj.mass.com_m,
        "num_collision_pieces": len(obj.parts),
        "parts": [
            {"name": p.name, "density_kg_m3": p.density_kg_m3, "volume_m3": float(p.mesh.volume)}
            for p in obj.parts
        ],
        "params": obj.params,
        "rgba": spec.rgba,
        "hydroelastic_modulus_pa": spec.contact.hydroelastic_modulus_pa,
        "mu_static": spec.contact.mu_static,
        "mu_dynamic": spec.contact.mu_dynamic,
        "relaxation_time_s": spec.contact.relaxation_time_s,
        "warnings": [],
    }
    write_object_dir(
        directory,
        model_name=obj.id,
        visual=union_mesh(meshes),
        collision=meshes,
        mass=obj.mass,
        rgba=spec.rgba,
        contact=spec.contact,
        meta=meta,
    )


class ObjectLibrary:
    """A set of objects, addressed by id.

    Use `ObjectLibrary.builtin()` for the procedural set (files generated on
    first `get()`) or `ObjectLibrary.from_dir()` for a folder of imports.
    """

    def __init__(self, root: Path, index: dict[str, tuple[str, str]], *, builtin: bool, infos=None):
        """Use `builtin()` or `from_dir()` instead.

        Args:
            root: Library folder.
            index: id -> (category, split).
            builtin: Whether missing objects are generated on demand.
            infos: Already loaded ObjectInfo per id.
        """
        self._root = Path(root)
        self._index = dict(index)
        self._builtin = builtin
        self._infos: dict[str, ObjectInfo] = dict(infos or {})
        self._content_hash: str | None = None

    @classmethod
    def builtin(cls, cache_dir: str | Path | None = None) -> "ObjectLibrary":
        """The procedural library (381 objects, 10 categories).

        Args:
            cache_dir: Cache root; default `$DRAKE_GRASP_CACHE` or
                `~/.cache/drake_grasp`. Files live in `objects-v<N>/` under it
                (N = GENERATOR_VERSION) and are written on first `get()`.
        """
        index = {}
        for oid in cat.builtin_ids():
            spec, i = cat.parse_object_id(oid)
            index[oid] = (spec.name, cat.split_of(i))
        return cls(builtin_library_dir(cache_dir), index, builtin=True)

    @classmethod
    def from_dir(cls, path: str | Path) -> "ObjectLibrary":
        """A library folder of object folders (as written by `import_mesh`).

        A folder that is itself one object (has meta.json) is a library of one.

        Raises:
            FileNotFoundError: `path` is not a folder.
            ValueError: No objects in it, or an object folder is broken.
        """
        root = Path(path).expanduser()
        if not root.is_dir():
            raise FileNotFoundError(f"object library folder {root} does not exist or is not a folder")
        if (root / META_FILE).exists():
            candidates = [root]
        else:
            # Hidden names are temporary folders of writes in progress.
            candidates = sorted(
                d
                for d in root.iterdir()
                if d.is_dir()
                and not d.name.startswith(".")
                and ((d / META_FILE).exists() or (d / MODEL_FILE).exists())
            )
        infos = {}
        for d in candidates:
            info = ObjectInfo.from_dir(d)
            infos[info.id] = info
        if not infos:
            raise ValueError(
                f"object library folder {root} holds no objects (expected sub-folders with {META_FILE} "
                f"and {MODEL_FILE}, e.g. made by import_mesh)"
            )
        index = {oid: (info.category, info.split) for oid, info in infos.items()}
        return cls(root if candidates != [root] else root.parent, index, builtin=False, infos=infos)

    @property
    def root(self) -> Path:
        """The library folder."""
        return self._root

    @property
    def is_builtin(self) -> bool:
        """Whether this is the procedural library."""
        return self._builtin

    def __len__(self) -> int:
        return len(self._index)

    def __contains__(self, object_id: object) -> bool:
        return object_id in self._index

    def categories(self) -> list[str]:
        """Sorted category names present in the library."""
        return sorted({category for category, _ in self._index.values()})

    def ids(self, split: str | None = None, category: str | None = None) -> list[str]:
        """Sorted ids, optionally only of one split and/or category.

        Raises:
            ValueError: Unknown split or category (lists the valid ones).
        """
        if split is not None and split not in cat.SPLITS:
            raise ValueError(f"split {split!r} is not one of {list(cat.SPLITS)}")
        if category is not None and category not in self.categories():
            raise ValueError(
                f"category {category!r} is not in this library; categories: {self.categories()}"
            )
        return sorted(
            oid
            for oid, (c, s) in self._index.items()
            if (split is None or s == split) and (category is None or c == category)
        )

    def get(self, object_id: str) -> ObjectInfo:
        """The object's info; builds the files of a procedural object if needed.

        Raises:
            UnknownObjectError: (a KeyError) the id is not in the library.
        """
        info = self._infos.get(object_id)
        if info is not None:
            return info
        if object_id not in self._index:
            some = sorted(self._index)[:: max(1, len(self._index) // 8)][:8]
            raise UnknownObjectError(
                f"unknown object id {object_id!r} in library {self._root}; "
                f"{len(self._index)} ids, e.g. {some}"
            )
        directory = self._root / object_id
        if self._builtin and not (directory / META_FILE).exists():
            write_procedural_object(object_id, directory)
        try:
            info = ObjectInfo.from_dir(directory)
        except ValueError as exc:
            hint = " (a corrupted cache entry: delete that folder to regenerate it)"
            hint = hint if self._builtin else ""
            raise ValueError(f"{exc}{hint}") from exc
        self._infos[object_id] = info
        return info

    def content_hash(self) -> str:
        """SHA-256 hex digest that changes when the library's objects change (cached).

        - The built-in procedural library: a hash of the generator version
          (`GENERATOR_VERSION`) and every (id, category, split), not of the generated
          files. The files are a deterministic function of the generator code, which the
          code version covers, so no object has to be generated to compute it.
        - A user library (`from_dir`): a hash over the sorted ids and, for each object,
          `provenance.tree_sha256` of its folder (every file's relative path and bytes:
          model.urdf, meshes, meta.json). Editing, adding or removing an object changes it.
        """
        if self._content_hash is None:
            h = hashlib.sha256()
            if self._builtin:
                h.update(f"builtin procedural library, generator v{cat.GENERATOR_VERSION}\n".encode())
                for oid in sorted(self._index):
                    category, split = self._index[oid]
                    h.update(f"{oid}\0{category}\0{split}\n".encode())
            else:
                from drake_grasp.core.provenance import tree_sha256

                h.update(b"user library\n")
                for oid in sorted(self._index):
                    h.update(f"{oid}\0{tree_sha256(self.get(oid).directory)}\n".encode())
            self._content_hash = h.hexdigest()
        return self._content_hash

    def __repr__(self) -> str:
        kind = "builtin" if self._builtin else "user"
        return f"ObjectLibrary({kind}, {len(self)} objects, root={str(self._root)!r})"


def load_library(objects_dir: str | Path | None = None) -> ObjectLibrary:
    """The builtin library for None, else the user library in `objects_dir`."""
    if objects_dir is None:
        return ObjectLibrary.builtin()
    return ObjectLibrary.from_dir(objects_dir)
