"""Tests of drake_grasp.objects: procedural library, files, Drake parsing, imports."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

from drake_grasp.objects import (
    CATEGORIES,
    GENERATOR_VERSION,
    ObjectInfo,
    ObjectLibrary,
    UnknownObjectError,
    builtin_ids,
    generate_object,
    import_mesh,
    load_library,
    write_procedural_object,
)

# One object per category for the (slower) Drake checks, plus a train one.
SAMPLE_INDICES = (0, 17)


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> ObjectLibrary:
    return ObjectLibrary.builtin(tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="module")
def sample_infos(library) -> list[ObjectInfo]:
    return [library.get(f"{c}_{i:03d}") for c in CATEGORIES for i in SAMPLE_INDICES]


def _plant_with_ground():
    from pydrake.geometry import (
        AddContactMaterial,
        AddRigidHydroelasticProperties,
        Box,
        ProximityProperties,
    )
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import AddMultibodyPlant, CoulombFriction, MultibodyPlantConfig
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    config = MultibodyPlantConfig(time_step=0.002, contact_model="hydroelastic_with_fallback")
    plant, scene_graph = AddMultibodyPlant(config, builder)
    props = ProximityProperties()
    AddRigidHydroelasticProperties(0.01, props)
    AddContactMaterial(friction=CoulombFriction(0.8, 0.7), properties=props)
    plant.RegisterCollisionGeometry(
        plant.world_body(), RigidTransform([0, 0, -0.05]), Box(6, 6, 0.1), "ground", props
    )
    return builder, plant


# ---------------------------------------------------------------- ids / split


def test_ids_split_and_categories(library):
    ids = library.ids()
    assert len(ids) == 381 == len(set(ids)) == len(library)
    assert ids == sorted(ids) == builtin_ids()
    assert len(library.ids(split="test")) == 50
    assert len(library.ids(split="train")) == 331
    assert library.categories() == sorted(CATEGORIES)
    assert len(CATEGORIES) == 10
    for category in CATEGORIES:
        test_ids = library.ids(split="test", category=category)
        assert test_ids == [f"{category}_{i:03d}" for i in range(5)]
    assert set(library.ids(split="test")).isdisjoint(library.ids(split="train"))


def test_bad_queries_name_the_problem(library):
    with pytest.raises(UnknownObjectError, match="unknown object id 'teapot_000'.*mug_"):
        library.get("teapot_000")
    with pytest.raises(KeyError):
        library.get("mug_999")
    with pytest.raises(ValueError, match="split 'val'"):
        library.ids(split="val")
    with pytest.raises(ValueError, match="category 'teapot'"):
        library.ids(category="teapot")


# ---------------------------------------------------------- procedural shapes


def test_all_instances_plausible_and_graspable():
    # In memory only (no files): fast enough to check every instance.
    for oid in builtin_ids():
        obj = generate_object(oid)
        assert 0.02 <= obj.mass.mass_kg <= 1.0, (oid, obj.mass.mass_kg)
        assert min(obj.extents_m) <= 0.075, (oid, obj.extents_m)
        assert max(obj.extents_m) <= 0.35, (oid, obj.extents_m)
        assert 1 <= len(obj.parts) <= 12, oid
        for part in obj.parts:
            assert part.mesh.is_watertight and part.mesh.is_convex, (oid, part.name)
        vertices = np.vstack([p.mesh.vertices for p in obj.parts])
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        # Canonical frame: origin at the bottom centre of the bounding box.
        np.testing.assert_allclose([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]], 0.0, atol=1e-9)
        eigenvalues = np.linalg.eigvalsh(obj.mass.inertia_kg_m2)
        assert eigenvalues.min() > 0, oid
        # Triangle inequality of principal moments (Drake rejects violations).
        assert eigenvalues[2] <= eigenvalues[0] + eigenvalues[1] + 1e-12, oid


def test_generation_is_deterministic(tmp_path):
    for oid in ("mug_003", "banana_020"):
        a, b = generate_object(oid), generate_object(oid)
        assert a.params == b.params
        for pa, pb in zip(a.parts, b.parts):
            np.testing.assert_array_equal(pa.mesh.vertices, pb.mesh.vertices)
            np.testing.assert_array_equal(pa.mesh.faces, pb.mesh.faces)
        write_procedural_object(oid, tmp_path / "one" / oid)
        write_procedural_object(oid, tmp_path / "two" / oid)
        files = sorted(p.name for p in (tmp_path / "one" / oid).iterdir())
        assert files == sorted(p.name for p in (tmp_path / "two" / oid).iterdir())
        for name in files:
            first = (tmp_path / "one" / oid / name).read_bytes()
            assert first == (tmp_path / "two" / oid / name).read_bytes(), (oid, name)
    # Different instances differ.
    assert generate_object("mug_000").params != generate_object("mug_001").params


# ---------------------------------------------------------------------- files


def test_files_and_meta(sample_infos, library):
    for info in sample_infos:
        directory = info.directory
        assert directory.parent == library.root
        assert library.root.name == f"objects-v{GENERATOR_VERSION}"
        meta = json.loads((directory / "meta.json").read_text())
        n = meta["num_collision_pieces"]
        assert {p.name for p in directory.iterdir()} == {"model.urdf", "meta.json", "visual.obj"} | {
            f"collision_{i:02d}.obj" for i in range(n)
        }
        assert (meta["id"], meta["split"], meta["category"]) == (info.id, info.split, info.category)
        assert meta["source"] == "procedural" and meta["generator_version"] == GENERATOR_VERSION
        assert meta["mass_kg"] == pytest.approx(info.mass_kg)
        assert len(meta["extents_m"]) == 3 and meta["volume_m3"] > 0
        sdf = info.model_path.read_text()
        assert "<drake:declare_convex/>" in sdf and "<drake:compliant_hydroelastic/>" in sdf
        assert sdf.count("<collision ") == n
    # No temporary folders left behind.
    assert not [p for p in library.root.iterdir() if p.name.startswith(".")]


def test_second_get_reuses_files(library, sample_infos):
    info = sample_infos[0]
    stamp = info.model_path.stat().st_mtime_ns
    fresh = ObjectLibrary.builtin(library.root.parent)
    assert fresh.get(info.id) == info
    assert info.model_path.stat().st_mtime_ns == stamp


def test_existing_target_is_kept(tmp_path):
    # A process that loses the race keeps the winner's folder and leaves no temp dir.
    target = tmp_path / "can_001"
    write_procedural_object("can_001", target)
    (target / "marker").write_text("first")
    write_procedural_object("can_001", target)
    assert (target / "marker").read_text() == "first"
    assert [p.name for p in tmp_path.iterdir()] == ["can_001"]


def test_cache_location_rule(tmp_path, monkeypatch):
    monkeypatch.setenv("DRAKE_GRASP_CACHE", str(tmp_path / "env_cache"))
    assert load_library(None).root == tmp_path / "env_cache" / f"objects-v{GENERATOR_VERSION}"
    monkeypatch.delenv("DRAKE_GRASP_CACHE")
    default = Path.home() / ".cache" / "drake_grasp" / f"objects-v{GENERATOR_VERSION}"
    assert load_library(None).root == default


# ---------------------------------------------------------------------- Drake


def test_models_parse_in_drake(sample_infos):
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    plant, _ = AddMultibodyPlantSceneGraph(DiagramBuilder(), time_step=0.002)
    for info in sample_infos:
        (model,) = Parser(plant).AddModels(str(info.model_path))
        assert plant.GetModelInstanceName(model) == info.id
        body = plant.GetBodyByName("body", model)
        assert body.default_mass() == pytest.approx(info.mass_kg)
    plant.Finalize()


def test_objects_drop_and_rest_on_ground(sample_infos):
    from pydrake.math import RigidTransform
    from pydrake.multibody.parsing import Parser
    from pydrake.systems.analysis import Simulator

    builder, plant = _plant_with_ground()
    infos = [i for i in sample_infos if i.split == "test"]  # one per category
    models = [Parser(plant).AddModels(str(info.model_path))[0] for info in infos]
    plant.Finalize()
    simulator = Simulator(builder.Build())
    context = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    for k, model in enumerate(models):
        pose = RigidTransform([0.45 * (k % 5) - 0.9, 0.5 * (k // 5) - 0.25, 0.03])
        plant.SetFreeBodyPose(context, plant.GetBodyByName("body", model), pose)
    simulator.AdvanceTo(0.5)
    for info, model in zip(infos, models):
        body = plant.GetBodyByName("body", model)
        com_z = plant.CalcCenterOfMassPositionInWorld(context, [model])[2]
        speed = np.linalg.norm(plant.EvalBodySpatialVelocityInWorld(context, body).translational())
        # Landed: COM above the ground, below where it started; nearly at rest.
        assert 0.0 < com_z < 0.03 + max(info.extents_m), (info.id, com_z)
        assert speed < 0.1, (info.id, speed)


# -------------------------------------------------------------------- imports


def _box_stl_cm(path: Path, extents_cm=(6.0, 4.0, 10.0)) -> Path:
    trimesh.creation.box(extents_cm).export(path)
    return path


def test_import_stl_in_cm(tmp_path):
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    mesh_file = _box_stl_cm(tmp_path / "box_cm.stl")
    lib_dir = tmp_path / "lib"
    info = import_mesh(mesh_file, name="my_box", library_dir=lib_dir, scale=0.01, density_kg_m3=500.0)
    assert info.id == "my_box" and info.split == "test" and info.category == "user"
    assert info.extents_m == pytest.approx((0.06, 0.04, 0.10), abs=1e-6)
    assert info.mass_kg == pytest.approx(500.0 * 0.06 * 0.04 * 0.10, rel=1e-4)
    meta = info.read_meta()
    assert meta["source"] == "box_cm.stl" and meta["num_collision_pieces"] == 1
    assert meta["warnings"] == []
    plant = MultibodyPlant(time_step=0.002)
    (model,) = Parser(plant).AddModels(str(info.model_path))
    assert plant.GetBodyByName("body", model).default_mass() == pytest.approx(info.mass_kg)

    lib = ObjectLibrary.from_dir(lib_dir)
    assert lib.ids() == ["my_box"] and lib.get("my_box") == info
    with pytest.raises(FileExistsError, match="my_box"):
        import_mesh(mesh_file, name="my_box", library_dir=lib_dir, scale=0.01)
    again = import_mesh(
        mesh_file, name="my_box", library_dir=lib_dir, scale=0.01, overwrite=True, split="train"
    )
    assert again.split == "train"
    assert [p.name for p in lib_dir.iterdir()] == ["my_box"]


def test_import_nonconvex_scene_uses_coacd(tmp_path):
    # An L-shaped glTF scene of two boxes: volume of the union, >1 convex piece.
    a = trimesh.creation.box([0.1, 0.03, 0.03])
    b = trimesh.creation.box([0.03, 0.03, 0.08])
    b.apply_translation([0.035, 0, 0.055])
    trimesh.Scene([a, b]).export(tmp_path / "ell.glb")
    info = import_mesh(
        tmp_path / "ell.glb", name="ell", library_dir=tmp_path / "lib", density_kg_m3=1000.0
    )
    meta = info.read_meta()
    assert meta["volume_basis"] == "repaired mesh"
    assert info.mass_kg == pytest.approx(1000.0 * (0.1 * 0.03 * 0.03 + 0.03 * 0.03 * 0.08), rel=1e-3)
    assert 2 <= meta["num_collision_pieces"] <= 12


def test_import_turns_gltf_y_up_to_z_up_as_drake_does(tmp_path):
    # A box tallest along y, as a glTF scanned object stands (glTF is y-up).
    box = trimesh.creation.box([0.03, 0.08, 0.05])
    trimesh.Scene([box]).export(tmp_path / "tall.glb")
    info = import_mesh(tmp_path / "tall.glb", name="tall", library_dir=tmp_path / "lib")
    assert list(info.extents_m) == pytest.approx([0.03, 0.05, 0.08])
    assert info.read_meta()["up_axis"] == "y"
    # Drake's own reading of the same scene (as .gltf, which it reads) stands it the same way.
    from pydrake.geometry import Mesh

    for name, data in trimesh.Scene([box]).export(file_type="gltf").items():
        (tmp_path / name).write_bytes(data)
    hull = Mesh(str(tmp_path / "model.gltf")).GetConvexHull()
    V = np.array([hull.vertex(i) for i in range(hull.num_vertices())])
    assert list(V.max(axis=0) - V.min(axis=0)) == pytest.approx([0.03, 0.05, 0.08])
    # The file's own axes kept when asked; OBJ/STL/PLY are z-up unless told.
    kept = import_mesh(tmp_path / "tall.glb", name="kept", library_dir=tmp_path / "lib",
                       up_axis="z")
    assert list(kept.extents_m) == pytest.approx([0.03, 0.08, 0.05])
    box.export(tmp_path / "tall.stl")
    stl = import_mesh(tmp_path / "tall.stl", name="stl", library_dir=tmp_path / "lib")
    assert list(stl.extents_m) == pytest.approx([0.03, 0.08, 0.05])
    assert stl.read_meta()["up_axis"] == "z"
    with pytest.raises(ValueError, match="up_axis 'x' is not one of"):
        import_mesh(tmp_path / "tall.stl", name="bad", library_dir=tmp_path / "lib", up_axis="x")


def test_import_millimetres_fails_with_scale_hint(tmp_path):
    mesh_file = tmp_path / "part_mm.stl"
    trimesh.creation.box((600.0, 400.0, 1000.0)).export(mesh_file)
    lib_dir = tmp_path / "lib"
    with pytest.raises(ValueError) as excinfo:
        import_mesh(mesh_file, name="part", library_dir=lib_dir)
    message = str(excinfo.value)
    assert str(mesh_file) in message and "--scale" in message and "0.001" in message
    assert not lib_dir.exists() or not any(lib_dir.iterdir())


def test_import_missing_and_garbage_files(tmp_path):
    lib_dir = tmp_path / "lib"
    missing = tmp_path / "nope.obj"
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        import_mesh(missing, name="nope", library_dir=lib_dir)
    rng = np.random.default_rng(0)
    for name in ("garbage.stl", "garbage.glb", "garbage.ply"):
        path = tmp_path / name
        path.write_bytes(rng.bytes(2000))
        with pytest.raises(ValueError, match=name):
            import_mesh(path, name="garbage", library_dir=lib_dir)
    text = tmp_path / "garbage.obj"
    text.write_text("this is not\na mesh\n")
    with pytest.raises(ValueError, match="garbage.obj"):
        import_mesh(text, name="garbage", library_dir=lib_dir)
    with pytest.raises(ValueError, match="garbage.txt"):
        (tmp_path / "garbage.txt").write_text("x")
        import_mesh(tmp_path / "garbage.txt", name="garbage", library_dir=lib_dir)
    # Nothing half-written.
    assert not lib_dir.exists() or not any(lib_dir.iterdir())


def test_failed_writes_leave_nothing(tmp_path, monkeypatch):
    import drake_grasp.objects.model_files as model_files

    real_write_obj = model_files.write_obj
    calls = []

    def failing_write_obj(*args, **kwargs):
        calls.append(args[0])
        if len(calls) % 2 == 0:  # the second file of each object
            raise OSError("disk full")
        return real_write_obj(*args, **kwargs)

    monkeypatch.setattr(model_files, "write_obj", failing_write_obj)
    lib_dir = tmp_path / "lib"
    with pytest.raises(OSError, match="disk full"):
        write_procedural_object("mug_000", lib_dir / "mug_000")
    with pytest.raises(OSError, match="disk full"):
        import_mesh(_box_stl_cm(tmp_path / "b.stl"), name="b", library_dir=lib_dir, scale=0.01)
    assert list(lib_dir.iterdir()) == []


def test_import_validates_arguments(tmp_path):
    mesh_file = _box_stl_cm(tmp_path / "box_cm.stl")
    for kwargs, pattern in [
        (dict(name="bad name"), "name"),
        (dict(name="ok", split="val"), "split"),
        (dict(name="ok", scale=0.0), "scale"),
        (dict(name="ok", max_convex_hulls=0), "max_convex_hulls"),
    ]:
        with pytest.raises(ValueError, match=pattern):
            import_mesh(mesh_file, library_dir=tmp_path / "lib", **{"scale": 0.01, **kwargs})


def test_from_dir_errors_name_the_folder(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match=re.escape(str(empty)) + ".*holds no objects"):
        ObjectLibrary.from_dir(empty)
    with pytest.raises(FileNotFoundError, match="missing_dir"):
        load_library(tmp_path / "missing_dir")
    lib_dir = tmp_path / "lib"
    info = import_mesh(_box_stl_cm(tmp_path / "b.stl"), name="b", library_dir=lib_dir, scale=0.01)
    meta_path = info.directory / "meta.json"
    meta_path.write_text("{not json")
    with pytest.raises(ValueError, match=f"{meta_path}.*JSON"):
        ObjectLibrary.from_dir(lib_dir)
    meta = {"id": "b", "category": "user", "split": "test", "mass_kg": -1, "extents_m": [0.1, 0.1, 0.1]}
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="mass_kg.*-1"):
        ObjectLibrary.from_dir(lib_dir)
    meta["mass_kg"] = 0.1
    meta_path.write_text(json.dumps(meta))
    info.model_path.write_text("<sdf><model name='b'>")
    with pytest.raises(ValueError, match="model.urdf"):
        ObjectLibrary.from_dir(lib_dir)
    os.remove(info.model_path)
    with pytest.raises(ValueError, match="model.urdf"):
        ObjectLibrary.from_dir(lib_dir)
