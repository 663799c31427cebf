"""Where the shipped models and scenario files live, and package:// registration.

`models/` and `diagrams/` sit at the top of the source tree; a built wheel carries
`diagrams/` and what runs by default from `models/` (`SHIPPED_MODELS`) inside the package
as `drake_grasp/_diagrams` and `drake_grasp/_models`. The earlier nets stay in the
repository's `models/` only (`REPOSITORY_WEIGHTS_SHA256`); `model_path` and
`missing_weights_message` say where one is when it is asked for and not installed.
Everything else finds them through this module, never through the working directory.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

PACKAGE_NAME = "drake_grasp"
_HERE = Path(__file__).resolve().parents[1]  # the drake_grasp package folder


def _first_existing(candidates: list[Path], marker: str) -> Path:
    for candidate in candidates:
        if (candidate / marker).exists():
            return candidate
    raise FileNotFoundError(
        f"cannot find {marker!r} in any of {[str(c) for c in candidates]}; "
        "is drake_grasp installed completely?"
    )


def models_dir() -> Path:
    """The folder that `package://drake_grasp/` maps to (holds package.xml)."""
    return _first_existing([_HERE / "_models", _HERE.parent / "models"], "package.xml")


def diagrams_dir() -> Path:
    """The folder holding the named `*.scenarios.yaml` files."""
    return _first_existing(
        [_HERE / "_diagrams", _HERE.parent / "diagrams"], "default.scenarios.yaml"
    )


def register_package(package_map) -> None:
    """Registers `package://drake_grasp/...` in a `pydrake.multibody.parsing.PackageMap`."""
    if not package_map.Contains(PACKAGE_NAME):
        package_map.Add(PACKAGE_NAME, str(models_dir()))


def make_parser(plant, model_name_prefix: str | None = None):
    """A `Parser` for `plant` that resolves `package://drake_grasp/...` URIs."""
    from pydrake.multibody.parsing import Parser

    parser = Parser(plant) if model_name_prefix is None else Parser(plant, model_name_prefix)
    register_package(parser.package_map())
    return parser


# --------------------------------------------------------------------------- what the wheel carries

SHIPPED_MODELS = (
    "package.xml", "ur5", "robotiq_2f85", "scene", "cnn-grid-bn12500-ep3-fp16", "gpd")
"""The entries of `models/` a built wheel carries under `drake_grasp/_models`: what runs by
default (the robot, hand and scene models, the default distance CNN, GPD's classifier).
pyproject.toml's force-include names the same entries (tests/test_wheel.py checks both)."""

REPOSITORY_WEIGHTS_SHA256 = {
    "cnn": "54eab575567d5dc5f4878e20be3cfe39c7aaacad4d650c1d7888f389af60a74d",
    "cnn-grid": "29246c0f0a782858eaca39d7bbbb1034f5d9aeff3770aeeddae2e22bbbf9782a",
    "cnn-grid-bn": "c2a76ad604d89b889f868415ab22133ff382af83f654c35310960815bc0f5ab3",
    "cnn-grid-bn12": "0362b4e1942b6f2283a1f573224f4109c1849866bfad8d43e488a4e44f6d81bd",
    "cnn-grid-bn12-ep5": "41d0885009829c97d1badf53725f0e5d4ab1845926353ec66ebb7aec736b0f43",
    "cnn-grid-bn12500": "77321f152100d513c4a583433f6cb28ca10d74de1602ff33f0a5fc1837fedf69",
    "cnn-grid-bn12500-ep3": "5b5777859799bfb9e6db379ce2a297f4b8a17ebd6a880fd5b51148c52ffc215d",
    "fcn-heightmap": "c31a4da57619a3deaee599b8130d03441141bb7f3209bd4d433debf2807323a5",
    "fcn-heightmap-all": "e3bd49ace502228d42550ac631dcafc46993f8b732797f32f2bf85cc3d80bfec",
}
"""The nets kept in the repository's `models/` only (earlier defaults and other heads,
selectable with `--weights`, among them the default in float32; 7 x 54 MB + 17 MB, not in
the wheel): folder -> sha256 of its
`weights.safetensors`, so that a record made with one names where it is
(`evaluation.replay.recorded_weights`)."""


def not_installed_message(relative: str, *, hint: str = "pass its path with --weights") -> str:
    """What to say when `models/<relative>` is not where the package looks for it.

    Args:
        relative: The file's path under `models/`, e.g. "cnn-grid-bn12/weights.safetensors".
        hint: What to do, for a file the repository holds.
    """
    rel = PurePosixPath(str(relative).replace("\\", "/"))
    folder = rel.parts[0] if rel.parts else ""
    if folder in REPOSITORY_WEIGHTS_SHA256:
        return (f"models/{rel} is not installed with the package (its models are in "
                f"{models_dir()}: {', '.join(SHIPPED_MODELS)}); it is in the drake_grasp "
                f"repository at models/{folder}/ — {hint}")
    return (f"models/{rel}: no such file in {models_dir()} (the package's models: "
            f"{', '.join(SHIPPED_MODELS)}; the repository's other nets: "
            f"{', '.join(REPOSITORY_WEIGHTS_SHA256)})")


def model_path(relative: str) -> Path:
    """`models_dir() / relative`, checked.

    Raises:
        FileNotFoundError: It is not there; for a net the repository holds and the wheel
            does not, the message names the file and its folder in the repository.
    """
    path = models_dir() / relative
    if not path.exists():
        raise FileNotFoundError(not_installed_message(relative))
    return path


def repository_model(path: str | Path) -> str | None:
    """For a path naming a repository-only net (`.../models/<net>/<file>` or
    `.../_models/<net>/<file>`, e.g. a `--weights` value), "<net>/<file>"; else None."""
    parts = PurePosixPath(str(path).replace("\\", "/")).parts
    for i in range(len(parts) - 2):
        if parts[i] in ("models", "_models") and parts[i + 1] in REPOSITORY_WEIGHTS_SHA256:
            return "/".join(parts[i + 1:])
    return None


def missing_weights_message(path: str | Path) -> str:
    """The error for a weights file `path` that does not exist: where the repository holds
    it when it names a net the wheel does not carry, else that there is no such file."""
    relative = repository_model(path)
    if relative is not None:
        return f"{path}: no such file; " + not_installed_message(relative)
    return f"{path}: no such weights file"
