"""Code version: package version + git commit in a checkout, '+unknown' when installed."""

import re
import subprocess

import pytest

from drake_grasp import __version__

from drake_grasp.core import provenance


@pytest.fixture
def fake_checkout(tmp_path, monkeypatch):
    repo = tmp_path / "repo"
    pkg = repo / "drake_grasp"
    pkg.mkdir(parents=True)
    (pkg / "x.py").write_text("A = 1\n")
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(git + ["init", "-q"], check=True)
    subprocess.run(git + ["add", "."], check=True)
    subprocess.run(git + ["commit", "-qm", "c"], check=True)
    monkeypatch.setattr(provenance, "_PACKAGE_DIR", pkg)
    provenance.git_commit.cache_clear()
    provenance.git_code_tree.cache_clear()
    yield pkg
    provenance.git_commit.cache_clear()
    provenance.git_code_tree.cache_clear()


def test_a_checkout_gives_the_commit(fake_checkout):
    head = subprocess.run(["git", "-C", str(fake_checkout.parent), "rev-parse", "HEAD"],
                          capture_output=True, text=True, check=True).stdout.strip()
    assert provenance.code_version() == f"{__version__}+git.{head[:12]}"


def test_two_different_uncommitted_edits_get_two_versions(fake_checkout):
    clean = provenance.code_version()
    (fake_checkout / "x.py").write_text("A = 2\n")
    provenance.git_commit.cache_clear()
    first = provenance.code_version()
    (fake_checkout / "x.py").write_text("A = 3\n")
    provenance.git_commit.cache_clear()
    second = provenance.code_version()
    assert re.fullmatch(re.escape(clean) + r"\+dirty\.[0-9a-f]{8}", first)
    assert first != second and second.startswith(clean + "+dirty.")


def test_the_code_tree_ignores_commits_outside_the_package(fake_checkout):
    """A commit that changes only tests keeps the code tree (a run resumes across it);
    one that changes the package, or an uncommitted edit, changes it."""
    repo = fake_checkout.parent
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]

    def commit(path, text):
        path.parent.mkdir(exist_ok=True)
        path.write_text(text)
        subprocess.run(git + ["add", "."], check=True)
        subprocess.run(git + ["commit", "-qm", "c"], check=True)
        provenance.git_commit.cache_clear()
        provenance.git_code_tree.cache_clear()
        return provenance.code_tree(), provenance.code_version()

    provenance.git_code_tree.cache_clear()
    tree0, version0 = provenance.code_tree(), provenance.code_version()
    assert re.fullmatch(re.escape(__version__) + r"\+tree\.[0-9a-f]{12}", tree0)
    tree1, version1 = commit(repo / "tests" / "test_x.py", "def test(): pass\n")
    assert tree1 == tree0 and version1 != version0
    # Markdown inside the package or models (a model card) is not code either,
    # committed or not.
    card = repo / "models" / "README.md"
    tree_md, _ = commit(card, "# card\n")
    assert tree_md == tree0
    card.write_text("# card, edited\n")
    provenance.git_commit.cache_clear()
    provenance.git_code_tree.cache_clear()
    assert provenance.code_tree() == tree0 and "dirty" not in provenance.code_version()
    tree2, _ = commit(fake_checkout / "x.py", "A = 2\n")
    assert tree2 != tree0
    (fake_checkout / "x.py").write_text("A = 3\n")
    provenance.git_commit.cache_clear()
    provenance.git_code_tree.cache_clear()
    assert re.fullmatch(re.escape(tree2) + r"\+dirty\.[0-9a-f]{8}", provenance.code_tree())
    provenance.git_code_tree.cache_clear()


def test_an_installed_package_says_unknown(tmp_path, monkeypatch):
    monkeypatch.setattr(provenance, "_PACKAGE_DIR", tmp_path / "site-packages" / "drake_grasp")
    provenance.git_commit.cache_clear()
    try:
        assert provenance.code_version() == f"{__version__}+unknown"
        provenance.git_code_tree.cache_clear()
        assert provenance.code_tree() == f"{__version__}+unknown"
    finally:
        provenance.git_code_tree.cache_clear()
        provenance.git_commit.cache_clear()


def test_checksums_name_a_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.bin"):
        provenance.file_sha256(tmp_path / "nope.bin")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "a.txt").write_text("a")
    h1 = provenance.tree_sha256(tmp_path / "d")
    (tmp_path / "d" / "a.txt").write_text("b")
    assert provenance.tree_sha256(tmp_path / "d") != h1
