"""What the wheel carries: the models that run by default and not the earlier nets, and
the error that names where a net is when it is asked for and not installed."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from drake_grasp.core import assets
from drake_grasp.core.provenance import file_sha256

REPO = Path(__file__).resolve().parents[1]


def _force_include() -> dict[str, str]:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    data = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    return data["tool"]["hatch"]["build"]["targets"]["wheel"]["force-include"]


def test_pyproject_ships_exactly_the_shipped_models():
    include = _force_include()
    models = {k.split("/", 1)[1]: v for k, v in include.items() if k.startswith("models/")}
    assert set(models) == set(assets.SHIPPED_MODELS)
    assert all(v == f"drake_grasp/_models/{k}" for k, v in models.items())
    assert include["diagrams"] == "drake_grasp/_diagrams"
    assert "models" not in include  # not the whole folder


def test_every_model_folder_is_shipped_or_listed_as_repository_only():
    entries = {p.name for p in (REPO / "models").iterdir()}
    assert entries == set(assets.SHIPPED_MODELS) | set(assets.REPOSITORY_WEIGHTS_SHA256)
    assert not set(assets.SHIPPED_MODELS) & set(assets.REPOSITORY_WEIGHTS_SHA256)


def test_repository_weights_sha256_match_the_files():
    for net, sha in assets.REPOSITORY_WEIGHTS_SHA256.items():
        assert file_sha256(REPO / "models" / net / "weights.safetensors") == sha, net


@pytest.fixture
def installed(tmp_path, monkeypatch):
    """An installed layout: drake_grasp/_models holding only what the wheel carries (empty
    files), and the working directory somewhere without the repository's models/."""
    pkg = tmp_path / "site-packages" / "drake_grasp"
    models = pkg / "_models"
    for entry in assets.SHIPPED_MODELS:
        src = REPO / "models" / entry
        if src.is_file():
            (models / entry).parent.mkdir(parents=True, exist_ok=True)
            (models / entry).write_text(src.read_text())
        else:
            for f in src.iterdir():
                (models / entry).mkdir(parents=True, exist_ok=True)
                (models / entry / f.name).write_bytes(b"")
    monkeypatch.setattr(assets, "_HERE", pkg)
    monkeypatch.chdir(tmp_path)
    assert assets.models_dir() == models
    return models


def _says_where(message: str, net: str) -> None:
    assert f"models/{net}/weights.safetensors is not installed with the package" in message
    assert f"it is in the drake_grasp repository at models/{net}/" in message


def test_model_path_names_a_net_that_is_not_installed(installed):
    assert assets.model_path("cnn-grid-bn12500-ep3-fp16/weights.safetensors") == \
        installed / "cnn-grid-bn12500-ep3-fp16" / "weights.safetensors"
    with pytest.raises(FileNotFoundError) as e:
        assets.model_path("cnn-grid-bn12/weights.safetensors")
    _says_where(str(e.value), "cnn-grid-bn12")
    assert "pass its path with --weights" in str(e.value)
    with pytest.raises(FileNotFoundError, match=r"models/nope/x: no such file in .*_models"):
        assets.model_path("nope/x")


def test_weights_path_of_a_net_that_is_not_installed(installed):
    from drake_grasp.cnn.weights_io import load_weights
    from drake_grasp.evaluation.experiments import option_patches

    with pytest.raises(FileNotFoundError) as e:
        load_weights("models/cnn-grid-bn12/weights.safetensors")
    _says_where(str(e.value), "cnn-grid-bn12")
    with pytest.raises(ValueError) as e:
        option_patches(weights="models/cnn/weights.safetensors")
    assert str(e.value).startswith("--weights models/cnn/weights.safetensors: ")
    _says_where(str(e.value), "cnn")
    # Any other missing file keeps the plain message.
    with pytest.raises(FileNotFoundError, match=r"^elsewhere\.safetensors: no such weights file$"):
        load_weights("elsewhere.safetensors")


def test_replay_of_a_net_that_is_not_installed_names_it(installed):
    from drake_grasp.evaluation.replay import _shipped_weights

    sha = assets.REPOSITORY_WEIGHTS_SHA256["cnn-grid-bn12-ep5"]
    with pytest.raises(ValueError) as e:
        _shipped_weights(sha, "R/run.json", "ctr", None)
    _says_where(str(e.value), "cnn-grid-bn12-ep5")
    assert "R/run.json: condition 'ctr'" in str(e.value) and sha in str(e.value)
    assert "replay from a checkout of the repository" in str(e.value)


def test_wheel_carries_the_default_net_and_not_the_earlier_ones(tmp_path):
    pytest.importorskip("hatchling", reason="builds offline with the test extra's hatchling")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(tmp_path), str(REPO)], check=True, timeout=600)
    (wheel,) = tmp_path.glob("drake_grasp-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for present in ("drake_grasp/_models/package.xml",
                    "drake_grasp/_models/cnn-grid-bn12500-ep3-fp16/weights.safetensors",
                    "drake_grasp/_models/gpd/weights.safetensors",
                    "drake_grasp/_models/ur5/ur5.urdf",
                    "drake_grasp/_models/robotiq_2f85/robotiq_2f85.urdf",
                    "drake_grasp/_models/scene/table.urdf",
                    "drake_grasp/_diagrams/default.scenarios.yaml",
                    "drake_grasp/core/assets.py"):
        assert present in names, present
    for net in assets.REPOSITORY_WEIGHTS_SHA256:
        assert not any(n.startswith(f"drake_grasp/_models/{net}/") for n in names), net
    tops = {n.split("/")[2] for n in names if n.startswith("drake_grasp/_models/")}
    assert tops == set(assets.SHIPPED_MODELS)
    # The default net is 56 MB of float32; the 8 earlier nets were another 340 MB.
    assert wheel.stat().st_size < 80e6
