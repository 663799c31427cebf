"""One run per folder, and files made durable before they are renamed into place.

One generator per folder. `generate_dataset` holds `generate.lock` (an exclusive `flock`
plus the owner's pid, host and start time in the file) for the whole run; a second
generator on the same folder is refused with an error naming the owner. A lock left by
a killed run (its pid no longer running on this host) is taken over with a message.
"""

from __future__ import annotations

import datetime
import json
import os
import socket
import sys
import uuid
from pathlib import Path



LOCK = "generate.lock"


# ----------------------------------------------------------------------------
# Durable files.


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(path: Path) -> None:
    """Makes a rename in `path` durable, where the OS allows fsync on a folder."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return  # e.g. Windows: folders cannot be opened
    try:
        os.fsync(fd)
    except OSError:
        pass  # some filesystems refuse fsync on a folder
    finally:
        os.close(fd)


def replace_durably(tmp: Path, path: Path) -> None:
    """fsync `tmp`, rename it to `path`, fsync the folder: after a crash `path` is either
    the old file or the complete new one."""
    _fsync_file(tmp)
    os.replace(tmp, path)
    fsync_dir(path.parent)


def process_tag() -> str:
    return f"{socket.gethostname()}-{os.getpid()}".replace("/", "_").replace(".", "_")


# ----------------------------------------------------------------------------
# One generator per folder.


class FolderInUseError(ValueError):
    """Another dataset generator holds the folder's lock (names the owner)."""


def _proc_start_ticks(pid: int) -> int | None:
    """Start time of a process in clock ticks since boot (Linux), to tell a reused pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    try:
        return int(stat.rsplit(")", 1)[1].split()[19])
    except (IndexError, ValueError):
        return None


def _pid_running(pid: int, start_ticks: int | None) -> bool:
    """Whether process `pid` (started at `start_ticks`, if known) runs on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # runs, as another user
    except OSError:
        return False
    if start_ticks is not None:
        now = _proc_start_ticks(pid)
        if now is not None and now != start_ticks:
            return False  # the pid was reused by another process
    return True


def describe_owner(owner: dict) -> str:
    return (f"pid {owner.get('pid')} on host {owner.get('host')}, started "
            f"{owner.get('started_at')}")


class GenerateLock:
    """The lock file of a dataset folder: one generator at a time (subclasses set `FILE`
    and `WHAT` to lock other kinds of run folders the same way).

    The file holds the owner's pid, host, start time and a run token (JSON) and is
    `flock`ed for the owner's lifetime, so the kernel releases it when the owner dies.
    Acquiring: a held flock -> `FolderInUseError` naming the owner; a file left by a
    process that no longer runs on this host -> taken over (`stale_owner` says whose);
    a file naming a process on another host -> refused (this host cannot tell whether it
    still runs; the message says to delete the file if it does not).
    """

    FILE = LOCK
    WHAT = "dataset generator"

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.path = self.folder / self.FILE
        self.token = uuid.uuid4().hex[:12]
        self.stale_owner: dict | None = None
        self._fd: int | None = None

    def _owner_record(self) -> dict:
        return {"pid": os.getpid(), "host": socket.gethostname(),
                "started_at": datetime.datetime.now(datetime.timezone.utc).isoformat(
                    timespec="seconds"),
                "start_ticks": _proc_start_ticks(os.getpid()), "token": self.token,
                "argv": list(sys.argv)}

    def _refuse(self, owner: dict, extra: str = "") -> FolderInUseError:
        return FolderInUseError(
            f"{self.folder}: another {self.WHAT} is using this folder "
            f"({describe_owner(owner)}; lock file {self.path}); wait for it to finish or "
            f"use another --out{extra}")

    def acquire(self) -> GenerateLock:
        import fcntl

        for _ in range(20):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                owner = self._read(fd)
                os.close(fd)
                raise self._refuse(owner) from None
            # An owner finishing right now unlinks the file it locked: retry on the new one.
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            previous = self._read(fd)
            if previous:
                if previous.get("host") != socket.gethostname():
                    os.close(fd)
                    raise self._refuse(previous, extra=(
                        f". This host ({socket.gethostname()}) cannot tell whether that "
                        f"process still runs; if it does not, delete {self.path} and re-run"))
                if _pid_running(int(previous.get("pid", -1)), previous.get("start_ticks")):
                    os.close(fd)
                    raise self._refuse(previous)
                self.stale_owner = previous
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(self._owner_record()) + "\n").encode(), 0)
            os.fsync(fd)
            self._fd = fd
            return self
        raise FolderInUseError(f"{self.folder}: could not take {self.path} (it kept changing)")

    @staticmethod
    def _read(fd: int) -> dict:
        data = b""
        while chunk := os.pread(fd, 65536, len(data)):
            data += chunk
        if not data.strip():
            return {}
        try:
            owner = json.loads(data)
        except ValueError:
            return {"pid": "?", "host": "?", "started_at": "? (unreadable lock file)"}
        return owner if isinstance(owner, dict) else {}

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            os.unlink(self.path)  # while still locked: nobody can take a file being removed
        except FileNotFoundError:
            pass
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> GenerateLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def temp_files(out: Path, token: str) -> list[Path]:
    """Temporary files of the run with this token (shards and manifest)."""
    return sorted(out.glob(f"*.{token}.*tmp"))
