"""analysis/ycb_library.py: scanned objects imported with their published masses."""

import pytest
import trimesh


def test_density_gives_the_mass_over_the_convex_hull(analysis_script, tmp_path):
    Y = analysis_script("ycb_library")
    box = trimesh.creation.box([0.04, 0.1, 0.06])
    for name, data in trimesh.Scene([box]).export(file_type="gltf").items():
        (tmp_path / name).write_bytes(data)
    density = Y.density_for(tmp_path / "model.gltf", 0.3)
    assert density * 0.04 * 0.1 * 0.06 == pytest.approx(0.3, rel=1e-6)


def test_a_folder_without_the_meshes_is_named(analysis_script, tmp_path, capsys):
    Y = analysis_script("ycb_library")
    assert Y.main([str(tmp_path), "--out", str(tmp_path / "lib")]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path) in err and "003_cracker_box_textured.gltf" in err
    assert not (tmp_path / "lib").exists()
