"""Where a result came from: the code version and content checksums of inputs.

Pure Python (no Drake, no torch), so every floor of the package can use it. The code
version is what run folders, dataset manifests and trained weights record, and what a
resumed run compares before it adds anything to an existing folder.
"""

from __future__ import annotations

import functools
import hashlib
import os
import subprocess
from pathlib import Path

from drake_grasp import __version__

_PACKAGE_DIR = Path(__file__).resolve().parents[1]  # the drake_grasp package folder

# What a trial's outcome can depend on in a checkout: the package, its models (weights,
# meshes, SDFs) and its diagrams (scenarios), less their Markdown (model cards, notes).
# Tests, docs and analysis scripts cannot.
CODE_PATHS = ("drake_grasp", "models", "diagrams")
_NOT_CODE = ":(exclude,glob)**/*.md"


@functools.lru_cache(maxsize=None)
def git_commit() -> str | None:
    """The commit of the checkout this package runs from, or None.

    None when the package is installed (site-packages) rather than run from a git
    checkout, or when git is unavailable. A checkout with uncommitted changes to the
    package, its models or diagrams gets "+dirty.<hash of the diff>" appended, because
    the commit alone would not say which code ran (Markdown there, e.g. a model card, is
    not code and leaves the version clean).
    """
    root = _PACKAGE_DIR.parent
    if not (root / ".git").exists():
        return None
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"],
                                capture_output=True, text=True, timeout=10, env=env)
        if commit.returncode != 0:
            return None
        diff = subprocess.run(["git", "-C", str(root), "diff", "HEAD", "--binary", "--",
                               *CODE_PATHS, _NOT_CODE],
                              capture_output=True, timeout=30, env=env)
    except (OSError, subprocess.SubprocessError):
        return None
    sha = commit.stdout.strip()[:12]
    if not sha:
        return None
    if diff.returncode != 0 or not diff.stdout.strip():
        return sha
    # Two different uncommitted edits must not share a version: name the edit by its hash.
    return f"{sha}+dirty.{hashlib.sha256(diff.stdout).hexdigest()[:8]}"


@functools.lru_cache(maxsize=None)
def git_code_tree() -> str | None:
    """A hash of the committed contents of `CODE_PATHS` (their files' git blob ids, Markdown
    left out), plus "+dirty.<hash of the diff>" for uncommitted changes to them; None
    outside a checkout.

    Unlike the commit, it stays the same across commits that change only tests, docs or
    analysis scripts, so a long run may be resumed after such commits.
    """
    root = _PACKAGE_DIR.parent
    if not (root / ".git").exists():
        return None
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}
    try:
        trees = subprocess.run(["git", "-C", str(root), "ls-tree", "-r", "HEAD", "--",
                                *CODE_PATHS], capture_output=True, text=True, timeout=10,
                               env=env)
    except (OSError, subprocess.SubprocessError):
        return None
    if trees.returncode != 0 or not trees.stdout.strip():
        return None
    blobs = [line for line in trees.stdout.splitlines() if not line.endswith(".md")]
    tree = hashlib.sha256("\n".join(blobs).encode()).hexdigest()[:12]
    commit = git_commit()
    dirty = commit.partition("+")[2] if commit else ""
    return f"{tree}+{dirty}" if dirty else tree


def code_tree() -> str:
    """Package version plus `git_code_tree` in a checkout; `code_version()` when installed.

    What a Monte Carlo run's identity compares on resume: the code that decides a trial,
    not the commit. Examples: "0.1.0+tree.1a2b3c4d5e6f", "0.1.0+tree.1a2b3c4d5e6f+dirty.9f8e7d6c".
    """
    tree = git_code_tree()
    return f"{__version__}+tree.{tree}" if tree else code_version()


def code_version() -> str:
    """Package version plus the git commit when run from a checkout.

    Examples: "0.1.0+git.1a2b3c4d5e6f", "0.1.0+git.1a2b3c4d5e6f+dirty.9f8e7d6c" (uncommitted
    changes to the package, models or diagrams, named by the hash of their diff),
    "0.1.0+unknown" (an installed package: the commit it was built from is not known).
    """
    commit = git_commit()
    return f"{__version__}+git.{commit}" if commit else f"{__version__}+unknown"


def file_sha256(path: str | os.PathLike, *, chunk: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file's bytes.

    Raises:
        FileNotFoundError: naming the file when it does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (expected a file to checksum)")
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def tree_sha256(root: str | os.PathLike, *, suffixes: tuple[str, ...] | None = None) -> str:
    """SHA-256 over the relative paths and bytes of every file under `root`, in sorted
    order (hidden files and folders skipped), so two folders with the same content have
    the same digest wherever they lie.

    Args:
        root: A folder.
        suffixes: Only files with one of these suffixes (e.g. (".urdf", ".obj")), or all.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder (expected a folder to checksum)")
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = path.relative_to(root)
        if any(part.startswith(".") for part in rel.parts):
            continue
        if suffixes is not None and path.suffix.lower() not in suffixes:
            continue
        h.update(rel.as_posix().encode() + b"\0")
        h.update(file_sha256(path).encode() + b"\n")
    return h.hexdigest()


# The packages whose builds decide a trial's floating point (physics, rendering, the nets,
# the generated object meshes and the ground-truth search).
MACHINE_PACKAGES = ("drake", "numpy", "scipy", "torch", "trimesh", "coacd", "manifold3d")


@functools.lru_cache(maxsize=None)
def machine() -> dict:
    """The machine a result was computed on: {"platform", "python", "cpu" (the model name,
    with family/model/stepping where /proc/cpuinfo has them), "cores", "packages" (the
    installed versions of `MACHINE_PACKAGES`, None when absent)}.

    A trial replays bit for bit only on the same kind of machine with the same builds: a
    different CPU generation can take other floating-point paths (measured on an AMD EPYC
    of CPU family 26: isolation trials kept every recorded outcome, clutter runs' poured
    piles settled up to 0.73 mm apart and later attempts changed; README
    *Reproducibility*). Informational, never part of a run's identity.
    """
    import platform
    from importlib import metadata

    cpu = platform.processor() or platform.machine()
    try:
        fields = {}
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if not line.strip():
                break  # the first processor's block
            key, _, value = line.partition(":")
            fields[key.strip()] = value.strip()
        if "model name" in fields:
            cpu = fields["model name"]
            extra = [f"{name} {fields[key]}" for key, name in
                     (("cpu family", "family"), ("model", "model"), ("stepping", "stepping"))
                     if key in fields]
            cpu = f"{cpu} ({', '.join(extra)})" if extra else cpu
    except OSError:
        pass
    packages = {}
    for name in MACHINE_PACKAGES:
        try:
            packages[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            packages[name] = None
    return {"platform": platform.platform(), "python": platform.python_version(),
            "cpu": cpu, "cores": os.cpu_count(), "packages": packages}
