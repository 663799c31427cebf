"""Modules loaded on their first use."""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType


def lazy_import(name: str) -> ModuleType:
    """The module `name`, executed only when one of its attributes is first read.

    The standard library's recipe (`importlib.util.LazyLoader`). Used for trimesh (with
    scipy, 0.6 s to import): the object library's metadata, which every Monte Carlo run
    reads for its identity, needs no mesh code; worker processes load it when a mesh is
    first touched.

    Raises:
        ModuleNotFoundError: `name` is not installed.
    """
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    if spec is None or spec.loader is None:
        raise ModuleNotFoundError(f"No module named {name!r}", name=name)
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module


__all__ = ["lazy_import"]
