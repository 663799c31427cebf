"""The drake-grasp command line: diagram pictures, errors, object import, scenarios."""

import json

import trimesh

from drake_grasp.cli.main import main


def test_diagram_writes_svg_or_dot(tmp_path, capsys):
    assert main(["diagram", "--scenario", "isolation", "--out", str(tmp_path / "station.svg")]) == 0
    written = capsys.readouterr().out.strip()
    text = open(written).read()
    assert "wrist_camera" in text and "diff_ik" in text


def test_bad_scenario_key_is_a_clean_error(tmp_path, capsys):
    code = main(["demo", "--scenario", "isolation", "--scenario-text", "{scene: {kindd: x}}",
                 "--out", str(tmp_path / "o")])
    assert code == 2
    assert "kindd" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_objects_import_and_list(tmp_path, capsys):
    mesh = trimesh.creation.box(extents=[0.05, 0.08, 0.03])
    path = tmp_path / "block.stl"
    mesh.export(path)
    lib = tmp_path / "lib"
    assert main(["objects", "import", str(path), "--name", "block", "--library", str(lib)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["id"] == "block" and 0.01 < info["mass_kg"] < 0.1
    assert main(["objects", "list", "--objects", str(lib)]) == 0
    assert capsys.readouterr().out.split() == ["block"]


def test_scenarios_lists_the_shipped_names(capsys):
    assert main(["scenarios"]) == 0
    names = capsys.readouterr().out.split()
    assert "isolation" in names and "clutter" in names


def test_gpd_generate_refuses_unknown_scene_kinds(tmp_path, capsys):
    code = main(["gpd-generate", "--scenes", "1", "--split", "train", "--out",
                 str(tmp_path / "d"), "--scene-kinds", "clutter,piles"])
    assert code == 2
    assert "--scene-kinds 'clutter,piles': expected a comma-separated list of isolation, random, clutter" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


def test_gpd_generate_passes_its_settling_limit_and_scene_kinds(tmp_path, monkeypatch, capsys):
    """gpd-generate --settle-max-time S --scene-kinds K: the data config gets both (they are
    part of a data folder's identity); a limit <= 0 is refused before anything runs."""
    from drake_grasp.learning import gpd_training

    seen = {}

    def fake_generate(**kwargs):
        seen.update(kwargs)
        return {"num_scenes": 0, "candidates": 0, "positives": 0}

    monkeypatch.setattr(gpd_training, "generate", fake_generate)
    assert main(["gpd-generate", "--scenes", "1", "--split", "train", "--out", str(tmp_path / "d"),
                 "--scene-kinds", "clutter", "--settle-max-time", "4"]) == 0
    assert seen["config"].settle_max_time_s == 4.0 and seen["config"].scene_kinds == ("clutter",)
    assert seen["config"].focus_categories == ()
    assert main(["gpd-generate", "--scenes", "1", "--split", "train", "--out", str(tmp_path / "f"),
                 "--focus-categories", "hammer,flashlight"]) == 0
    assert seen["config"].focus_categories == ("hammer", "flashlight")
    assert main(["gpd-generate", "--scenes", "1", "--split", "train", "--out", str(tmp_path / "e"),
                 "--settle-max-time", "0"]) == 2
    assert "--settle-max-time 0.0: expected seconds > 0" in capsys.readouterr().err
