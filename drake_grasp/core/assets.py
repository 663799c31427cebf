"""Where the shipped models and scenario files live, and package:// registration.

`models/` and `diagrams/` sit at the top of the source tree; a built wheel carries
them inside the package as `drake_grasp/_models` and `drake_grasp/_diagrams`.
Everything else finds them through this module, never through the working directory.
"""

from __future__ import annotations

from pathlib import Path

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
