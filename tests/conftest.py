"""Shared fixtures: the built-in object library in a per-session cache folder."""

import os

import pytest


@pytest.fixture(scope="session")
def library(tmp_path_factory):
    from drake_grasp.objects import ObjectLibrary

    cache = os.environ.get("DRAKE_GRASP_CACHE")
    root = cache if cache else tmp_path_factory.mktemp("object_cache")
    return ObjectLibrary.builtin(cache_dir=root)
