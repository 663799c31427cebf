"""The documentation: the MkDocs site builds with --strict (no broken link, no docstring
griffe warns about), holds the pages it promises, and the README stays the front door:
at most 400 lines, its quick start as `.ci/run` reads it, and every `drake-grasp`
command it names exists."""

import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

GUIDE_PAGES = ["station", "scenarios", "policies", "judge", "experiments", "records",
               "grasp-lab", "data-training", "timing", "bridge", "physics", "benchmarks",
               "bad-input", "reproducibility", "cli"]


def _nav_files(nav) -> list[str]:
    files = []
    for entry in nav:
        value = next(iter(entry.values())) if isinstance(entry, dict) else entry
        files.extend(_nav_files(value) if isinstance(value, list) else [value])
    return files


def test_the_site_builds_strict_with_every_page(tmp_path):
    site = tmp_path / "site"
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
         str(ROOT / "mkdocs.yml"), "--site-dir", str(site)],
        cwd=ROOT, capture_output=True, text=True, timeout=300)
    seconds = time.perf_counter() - start
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "WARNING" not in proc.stderr, proc.stderr[-4000:]
    assert seconds < 60, f"mkdocs build took {seconds:.0f} s"

    for page in ["index", "getting-started", "results", "architecture", "api",
                 "research/index", "reference-results-history", "ci-timings"]:
        assert (site / f"{page}.html").is_file(), page
    for page in GUIDE_PAGES:
        assert (site / "guide" / f"{page}.html").is_file(), page
    # Every research page is built and listed in the research log's index.
    research = sorted(p.stem for p in (ROOT / "docs" / "research").glob("*.md") if p.stem != "index")
    assert len(research) >= 24
    index = (site / "research" / "index.html").read_text(encoding="utf-8")
    for stem in research:
        assert (site / "research" / f"{stem}.html").is_file(), stem
        assert f'href="{stem}.html"' in index, stem

    # The API page is rendered from the docstrings (mkdocstrings), not written by hand.
    api = (site / "api.html").read_text(encoding="utf-8")
    assert 'id="drake_grasp.api.MakeGraspStation"' in api
    assert 'id="drake_grasp.policies.plugins.make_policy_system"' in api
    assert "X_WG_desired" in api and "the grasp frame" in api
    assert 'id="drake_grasp.policies.evaluator.DistanceEvaluator"' in api

    # Offline: no page loads a script, a style sheet or a font from the network.
    for page in site.rglob("*.html"):
        text = page.read_text(encoding="utf-8")
        assert not re.search(r'<(script|link)[^>]+(src|href)="(https?:)?//', text), page


def test_every_docs_page_is_in_the_nav():
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))
    assert config["use_directory_urls"] is False
    nav = set(_nav_files(config["nav"]))
    pages = {p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").rglob("*.md")}
    assert pages == nav, (sorted(pages - nav), sorted(nav - pages))
    for page in GUIDE_PAGES:
        assert f"guide/{page}.md" in nav


def test_the_readme_is_at_most_400_lines():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= 400, f"README.md has {n} lines (at most 400; the rest belongs in docs/)"


def test_the_readmes_quick_start_is_what_ci_reads():
    """`.ci/run` runs the first two ```bash blocks of *Quick start*, one command line each."""
    text = README.read_text(encoding="utf-8")
    section = re.search(r"^## Quick start\n(.*?)(?=^## )", text, re.S | re.M)
    assert section, "README.md: no '## Quick start' section"
    blocks = re.findall(r"^```bash\n(.*?)^```", section.group(1), re.S | re.M)
    assert len(blocks) >= 2
    lines = [[l for l in b.strip().splitlines() if l.strip()] for b in blocks[:2]]
    assert lines == [
        ['python3 -m venv .venv && .venv/bin/pip install ".[test]" && .venv/bin/drake-grasp '
         'demo --policy ctr --scenario clutter --seed 0 --out out/demo'],
        [".venv/bin/python -m pytest -q tests"]]


def _subcommands(parser) -> dict:
    """name -> its sub-parser, from a parser's subcommand action ({} when it has none)."""
    for action in parser._actions:
        if action.__class__.__name__ == "_SubParsersAction":
            return dict(action.choices)
    return {}


def _readme_commands() -> list[tuple[str, ...]]:
    """Each `drake-grasp COMMAND [SUBCOMMAND]` the README names (the second word kept only
    where COMMAND has subcommands, e.g. `bridge episode`, `objects list`)."""
    from drake_grasp.cli.main import build_parser

    top = _subcommands(build_parser())
    text = README.read_text(encoding="utf-8")
    found = set()
    for m in re.finditer(r"drake-grasp((?: [a-z][a-z0-9-]*){1,2})", text):
        words = m.group(1).split()
        has_sub = words[0] in top and _subcommands(top[words[0]])
        found.add(tuple(words[:2] if has_sub else words[:1]))
    return sorted(found)


def test_the_readme_names_every_command():
    from drake_grasp.cli.main import build_parser

    named = set(_readme_commands())
    for name, parser in _subcommands(build_parser()).items():
        subs = _subcommands(parser)
        expected = {(name, sub) for sub in subs} if subs else {(name,)}
        assert expected <= named, f"README.md does not name {sorted(expected - named)}"


@pytest.mark.parametrize("command", _readme_commands(), ids=" ".join)
def test_each_command_the_readme_names_exists(command, capsys):
    from drake_grasp.cli.main import main

    with pytest.raises(SystemExit) as exit_:
        main([*command, "--help"])
    assert exit_.value.code == 0, f"drake-grasp {' '.join(command)} --help"
    assert f"usage: drake-grasp {' '.join(command)}" in capsys.readouterr().out


def test_the_readmes_links_into_docs_exist():
    text = README.read_text(encoding="utf-8")
    links = re.findall(r"\]\((docs/[^)#]+)", text)
    assert len(links) >= 20
    for link in links:
        assert (ROOT / link).is_file(), f"README.md links to {link}, which does not exist"
