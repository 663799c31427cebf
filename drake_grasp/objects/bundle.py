"""A user object library carried by content to machines that cannot see its folder.

On a cluster without a shared filesystem, `evaluate --objects DIR --scheduler ADDR` packs
DIR into an `ObjectBundle` (its `ObjectLibrary.content_hash` and a gzipped tar of the
folder), scatters it to the workers once, and each worker unpacks it into its own cache,
`$DRAKE_GRASP_CACHE` (default `~/.cache/drake_grasp`) `/object-bundles/<hash>/`, and loads
it from there. The unpacked library must hash to the bundle's hash, or the worker refuses
it by name: the records of a run name the library by that hash. The built-in objects need
no bundle (every worker generates the same files from the same code).
"""

from __future__ import annotations

import io
import os
import shutil
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class ObjectBundle:
    """An object library's folder as bytes, with the content hash it must load with."""

    content_hash: str
    archive: bytes  # gzipped tar of the folder's files, paths relative to it
    source: str  # the folder it was made from, on the machine that made it (for messages)


def make_bundle(objects_dir: str | os.PathLike) -> ObjectBundle:
    """Packs a user library folder (`objects import` output) into a bundle.

    Raises:
        FileNotFoundError / ValueError: as `load_library` does for a bad folder.
    """
    from drake_grasp.objects.library import load_library

    folder = Path(objects_dir)
    content_hash = load_library(folder).content_hash()
    buf = io.BytesIO()
    # Links are stored as the files they point to, as the library's hash reads them.
    with tarfile.open(fileobj=buf, mode="w:gz", dereference=True) as tar:
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            tar.add(path, arcname=path.relative_to(folder).as_posix(), recursive=False)
    return ObjectBundle(content_hash=content_hash, archive=buf.getvalue(), source=str(folder))


def _cache_root() -> Path:
    base = os.environ.get("DRAKE_GRASP_CACHE") or Path.home() / ".cache" / "drake_grasp"
    return Path(base) / "object-bundles"


def library_from_bundle(bundle: ObjectBundle, cache_root: str | os.PathLike | None = None):
    """The bundle's library, unpacked into this machine's cache (once per hash).

    Raises:
        ValueError: The unpacked library's content hash is not the bundle's (named).
    """
    from drake_grasp.objects.library import load_library

    root = Path(cache_root) if cache_root is not None else _cache_root()
    target = root / bundle.content_hash
    if not target.is_dir():
        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{bundle.content_hash[:12]}.", dir=root))
        try:
            with tarfile.open(fileobj=io.BytesIO(bundle.archive), mode="r:gz") as tar:
                if hasattr(tarfile, "data_filter"):  # no absolute paths, links or devices
                    tar.extractall(tmp, filter="data")
                else:  # pragma: no cover - Pythons before the filters; made by make_bundle
                    tar.extractall(tmp)
            try:
                os.rename(tmp, target)  # atomic; another worker may have been first
            except OSError:
                if not target.is_dir():
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    library = load_library(target)
    got = library.content_hash()
    if got != bundle.content_hash:
        raise ValueError(f"object library {bundle.source} (shipped by the driver) unpacked into "
                         f"{target} has content hash {got}, expected {bundle.content_hash}; "
                         f"delete {target} and run again")
    return library
