"""The public API: every name documented, its pdoc reference page builds, and every
Python block of the README (its how-tos) runs as written."""

import inspect
import re
import runpy
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_every_public_name_has_a_docstring():
    import drake_grasp.api as api

    assert len(api.__all__) >= 20
    for name in api.__all__:
        obj = getattr(api, name)
        if isinstance(obj, dict):  # EXPERIMENTS: documented in the module docstring
            assert name in api.__doc__
            continue
        doc = inspect.getdoc(obj)
        assert doc and len(doc.strip()) > 20, f"drake_grasp.api.{name} has no docstring"


def test_the_api_reference_page_builds_with_pdoc(tmp_path):
    import pdoc

    import drake_grasp.api as api

    pdoc.pdoc("drake_grasp.api", "drake_grasp.policies.plugins", output_directory=tmp_path)
    page = (tmp_path / "drake_grasp" / "api.html").read_text()
    for name in api.__all__:
        assert name in page, name
    assert "MakeGraspStation" in page and "X_WG_desired" in page
    assert (tmp_path / "drake_grasp" / "policies" / "plugins.html").is_file()


# What each of the README's Python blocks must print (and write), by the heading above it.
# Every block needs an entry: a new block without one fails `test_every_readme_block_is_checked`.
README_BLOCKS = {
    "Put the station in your own Diagram": {
        "prints": [r"wrist depth image \(64, 64\) nearest \d\.\d{3} m"],
        "writes": [],
    },
    "Run a Monte Carlo study": {
        "prints": [r"scripted: [01] of 1 lifted; 95% interval \[", r"init: median final distance \d+ mm",
                   r"report: out/smoke/report\.md"],
        "writes": ["out/smoke/run.json", "out/smoke/report.md"],
    },
    "Run it on a cluster": {
        "prints": [r"\b2 records, written by this process in out/smoke-dask"],
        "writes": ["out/smoke-dask/run.json", "out/smoke-dask/report.md",
                   "out/smoke-dask/trials.parquet"],
    },
    "Run your own policy next to CTR and GPD": {
        "prints": [r"lifted: (True|False) final distance \[m\]: ", r"ctr: [01] of 1 lifted",
                   r"gpd: [01] of 1 lifted", r"centroid_policy\.make_policy: [01] of 1 lifted"],
        "writes": ["out/byop/run.json"],
    },
    "Test one system alone with FixValue and Eval": {
        "prints": [r"predicted distances \[m\]: \[(\s*\d\.\d+){8}\s*\]"],
        "writes": [],
    },
}


def readme_python_blocks() -> dict[str, str]:
    """The README's ```python blocks, each keyed by the nearest heading above it."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks, heading, fence = {}, None, None
    for line in text.splitlines(keepends=True):
        if fence is not None:
            if line.startswith("```"):
                if fence[0] == "python":
                    assert heading not in blocks, f"README.md: two Python blocks under {heading!r}"
                    blocks[heading] = "".join(fence[1])
                fence = None
            else:
                fence[1].append(line)
        elif line.startswith("```"):
            fence = (line[3:].strip(), [])
        elif line.startswith("#"):
            heading = line.lstrip("#").strip()
    return blocks


def test_every_readme_block_is_checked():
    blocks = readme_python_blocks()
    assert len(blocks) >= 4, sorted(blocks)
    assert sorted(blocks) == sorted(README_BLOCKS)


@pytest.mark.slow
@pytest.mark.parametrize("heading", sorted(README_BLOCKS))
def test_the_readmes_python_block_runs(heading, tmp_path, monkeypatch, capsys):
    """Each block runs as written from the repository root: here from a folder that holds
    only `examples/` (a link), so that everything it writes lands under tmp_path."""
    import sys

    block = readme_python_blocks()[heading]
    (tmp_path / "examples").symlink_to(ROOT / "examples", target_is_directory=True)
    script = tmp_path / "block.py"
    script.write_text(block)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))  # a block may add to it
    modules = set(sys.modules)
    try:
        runpy.run_path(str(script), run_name="__main__")
    finally:
        for name in set(sys.modules) - modules:  # e.g. centroid_policy from tmp_path
            if getattr(sys.modules[name], "__file__", "") and str(tmp_path) in str(
                    sys.modules[name].__file__):
                del sys.modules[name]
    out = capsys.readouterr().out
    for pattern in README_BLOCKS[heading]["prints"]:
        assert re.search(pattern, out), f"{heading}: no {pattern!r} in\n{out}"
    for path in README_BLOCKS[heading]["writes"]:
        assert (tmp_path / path).is_file(), f"{heading}: {path} not written"
