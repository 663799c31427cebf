"""Each trial in a forked child of a warm worker: crash isolation and constant memory.

`run_forked(fn, *args)` calls `fn` in a child process forked from this one and returns
what it returned. The child starts with everything the worker has loaded (pydrake, torch,
the CNN, the object library and its meshes) and builds and simulates its trial's Diagram;
whatever it allocates - including the Python LeafSystems that drake 1.51 never frees
(Drake issues 22515, 24162) - goes when it exits, so the worker's memory does not grow
with the trials it has run. A child that dies (a segfault in a native library, the
kernel's out-of-memory killer, `os._exit`) raises `TrialProcessDied` in the worker, naming
the signal or exit code and the last stage the child reported with `stage(name)`; the
worker records that and goes on. TRI's lbm_eval runs its Drake episodes in forked
processes for the same reasons.

POSIX only (`os.fork`). The worker should not have run torch on several threads or made
a GL context before forking (children inherit them in an undefined state): trial workers
load the CNN with one thread and render only in children.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import warnings

_HEADER = struct.Struct("!cQ")  # kind (b"S": stage, b"R": result), payload length
_CHILD_FD: int | None = None  # the pipe to the worker, in a forked child


class TrialProcessDied(RuntimeError):
    """A forked trial process ended without returning a result."""

    def __init__(self, message: str, *, stage: str, signal_name: str | None,
                 exit_code: int | None) -> None:
        super().__init__(message)
        self.stage = stage
        self.signal_name = signal_name
        self.exit_code = exit_code


def available() -> bool:
    """Whether this platform can fork (POSIX)."""
    return hasattr(os, "fork")


def stage(name: str) -> None:
    """Reports the stage a forked trial has reached (named when it dies); no-op outside
    a forked child."""
    if _CHILD_FD is not None:
        _send(_CHILD_FD, b"S", name.encode())


def _send(fd: int, kind: bytes, payload: bytes) -> None:
    data = _HEADER.pack(kind, len(payload)) + payload
    while data:
        data = data[os.write(fd, data):]


def _read_exact(fd: int, n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = os.read(fd, min(left, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _child(fd: int, fn, args, kwargs) -> None:
    global _CHILD_FD
    _CHILD_FD = fd
    code = 0
    try:
        try:
            payload = pickle.dumps(("ok", fn(*args, **kwargs)))
        except BaseException as e:  # noqa: BLE001 - handed to the worker to raise there
            try:
                payload = pickle.dumps(("raised", e))
            except Exception:  # noqa: BLE001 - an exception that does not pickle
                payload = pickle.dumps(("raised", RuntimeError(f"{type(e).__name__}: {e}")))
        _send(fd, b"R", payload)
    except BaseException:  # noqa: BLE001 - nothing may unwind into the worker's code
        code = 70
    finally:
        os._exit(code)  # no atexit handlers, no flushing of the worker's buffers


def run_forked(fn, *args, **kwargs):
    """`fn(*args, **kwargs)` run in a forked child; its return value (pickled back).

    Raises:
        TrialProcessDied: The child died or exited without a result (signal or exit code
            and its last `stage` named).
        BaseException: What `fn` raised in the child, re-raised here.
    """
    read_fd, write_fd = os.pipe()
    with warnings.catch_warnings():
        # Python 3.12+ warns when a process with threads forks; the child runs only the
        # trial and leaves with os._exit.
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # pragma: no cover - the child; coverage of children is not collected
        os.close(read_fd)
        _child(write_fd, fn, args, kwargs)
    os.close(write_fd)
    last_stage, result = "start", None
    try:
        while True:
            header = _read_exact(read_fd, _HEADER.size)
            if header is None:
                break
            kind, n = _HEADER.unpack(header)
            payload = _read_exact(read_fd, n)
            if payload is None:
                break
            if kind == b"S":
                last_stage = payload.decode()
            else:
                result = pickle.loads(payload)
    finally:
        os.close(read_fd)
        _, status = os.waitpid(pid, 0)
    if result is not None:
        outcome, value = result
        if outcome == "ok":
            return value
        raise value
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        name = signal.Signals(sig).name if sig in signal.valid_signals() else str(sig)
        raise TrialProcessDied(f"trial process killed by signal {name} ({sig}) in stage "
                               f"{last_stage!r}", stage=last_stage, signal_name=name,
                               exit_code=None)
    code = os.WEXITSTATUS(status) if os.WIFEXITED(status) else None
    raise TrialProcessDied(f"trial process exited with code {code} without a result in stage "
                           f"{last_stage!r}", stage=last_stage, signal_name=None, exit_code=code)
