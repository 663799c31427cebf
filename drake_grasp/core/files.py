"""Files written whole or not at all, and JSON printed and saved as one text."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Writes `data` to `path` via a temporary file in the same folder and `os.replace`.

    Readers see either the old file or the complete new one, never a partial file, and a
    crash leaves at most a hidden `.<name>.*.tmp` file that no reader lists.

    Args:
        path: Destination file; its folder is created when missing.
        data: File contents.

    Returns:
        The destination path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            # A rename after a power cut could otherwise point at an empty file.
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(e, OSError) and e.filename is None:  # a full disk names no file
            message = f"cannot write {path}: {e.strerror or e}"
            raise (OSError(e.errno, message) if e.errno else OSError(message)) from e
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """`atomic_write_bytes` for UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def print_json(data: dict, out: str | os.PathLike | None = None) -> str:
    """Prints `data` as indented JSON and, with `out`, writes the same text (and a final
    newline) there atomically: how a measurement script reports its result."""
    text = json.dumps(data, indent=1)
    print(text)
    if out:
        atomic_write_text(out, text + "\n")
    return text
