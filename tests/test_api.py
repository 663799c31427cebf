"""The public API: every name documented, its pdoc reference page builds, and the
README's "Python usage" block runs as written."""

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


def _python_usage_block() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = re.search(r"^## Python usage\n(.*?)(?=^## )", text, re.S | re.M)
    assert section, "README.md: no '## Python usage' section"
    blocks = re.findall(r"^```python\n(.*?)^```", section.group(1), re.S | re.M)
    assert len(blocks) == 1
    return blocks[0]


@pytest.mark.slow
def test_the_readmes_python_usage_block_runs(tmp_path, monkeypatch, capsys):
    script = tmp_path / "usage.py"
    script.write_text(_python_usage_block())
    monkeypatch.chdir(tmp_path)  # it writes out/api-example here
    runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr().out
    assert "wrist depth image (64, 64)" in out
    assert re.search(r"lifted: (True|False) final distance \[m\]: ", out)
    assert re.search(r"scripted: [01] of 1 lifted", out)
    assert (tmp_path / "out" / "api-example" / "run.json").is_file()
