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
load the CNN with one thread and render only in children. A child still running after
`DEFAULT_TIMEOUT_S` is killed and recorded, and on Linux a child dies with its worker.
"""

from __future__ import annotations

import os
import pickle
import select
import signal
import struct
import sys
import threading
import time
import warnings

_HEADER = struct.Struct("!cQ")  # kind (b"S": stage, b"R": result), payload length
_CHILD_FD: int | None = None  # the pipe to the worker, in a forked child
_FORK_LOCK = threading.Lock()
# A trial still running after this long is killed and recorded (a hung child would hold
# its worker for ever): 30 minutes, about 100 times a trial's usual wall time.
DEFAULT_TIMEOUT_S = 1800.0


class TrialProcessDied(RuntimeError):
    """A forked trial process ended without returning a result."""

    def __init__(self, message: str, *, stage: str, signal_name: str | None,
                 exit_code: int | None) -> None:
        super().__init__(message)
        self.stage = stage
        self.signal_name = signal_name
        self.exit_code = exit_code

    def __reduce__(self):  # pickles with its keyword arguments (Dask, process pools)
        return (_died, (str(self), self.stage, self.signal_name, self.exit_code))


def _died(message, stage, signal_name, exit_code) -> TrialProcessDied:
    return TrialProcessDied(message, stage=stage, signal_name=signal_name, exit_code=exit_code)


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


def _read_exact(fd: int, n: int, deadline: float | None) -> bytes | None:
    """`n` bytes from the pipe; None at end of file. Raises TimeoutError past `deadline`
    (time.monotonic())."""
    chunks, left = [], n
    while left:
        if deadline is not None:
            wait = deadline - time.monotonic()
            if wait <= 0 or not select.select([fd], [], [], wait)[0]:
                raise TimeoutError
        chunk = os.read(fd, min(left, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _die_with_parent() -> None:
    """Linux: the child gets SIGKILL when its worker dies, instead of simulating on."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass


def _child(fd: int, fn, args, kwargs) -> None:
    global _CHILD_FD, _FORK_LOCK
    _CHILD_FD = fd
    _FORK_LOCK = threading.Lock()  # the worker's was held when it forked
    code = 0
    try:
        _die_with_parent()
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
        for stream in (sys.stdout, sys.stderr):  # what the trial printed
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - a closed stream: nothing to keep
                pass
        os._exit(code)  # no atexit handlers, nothing of the worker's run twice


def _fork() -> int:
    for stream in (sys.stdout, sys.stderr):  # else the child would print them again
        try:
            stream.flush()
        except Exception:  # noqa: BLE001
            pass
    with warnings.catch_warnings():
        # Python 3.12+ warns when a process with threads forks; the child runs only the
        # trial and leaves with os._exit.
        warnings.simplefilter("ignore", DeprecationWarning)
        return os.fork()


def run_forked(fn, *args, stage: str = "start", timeout_s: float | None = DEFAULT_TIMEOUT_S,
               **kwargs):
    """`fn(*args, **kwargs)` run in a forked child; its return value (pickled back).

    `stage` names the child's stage until it reports one (`stage()`); a child still running
    after `timeout_s` seconds (None: no limit) is killed. Threads of one process may call
    it at once: the pipe is made and the fork done under a lock, so that no child holds
    another's pipe open.

    Raises:
        TrialProcessDied: The child could not be forked, died, exited without a result or
            was killed at the timeout (named, with its last stage).
        BaseException: What `fn` raised in the child, re-raised here.
    """
    with _FORK_LOCK:
        read_fd, write_fd = os.pipe()
        try:
            pid = _fork()
        except OSError as e:
            os.close(read_fd)
            os.close(write_fd)
            raise TrialProcessDied(f"could not fork a trial process: {e}", stage=stage,
                                   signal_name=None, exit_code=None) from e
        if pid == 0:  # pragma: no cover - the child; coverage of children is not collected
            os.close(read_fd)
            _child(write_fd, fn, args, kwargs)
        os.close(write_fd)
    deadline = None if timeout_s is None else time.monotonic() + float(timeout_s)
    last_stage, result, timed_out = stage, None, False
    try:
        while result is None:
            header = _read_exact(read_fd, _HEADER.size, deadline)
            payload = None if header is None else _read_exact(
                read_fd, _HEADER.unpack(header)[1], deadline)
            if payload is None:
                break
            if _HEADER.unpack(header)[0] == b"S":
                last_stage = payload.decode()
            else:
                result = pickle.loads(payload)
    except TimeoutError:
        timed_out = True
        os.kill(pid, signal.SIGKILL)
    finally:
        os.close(read_fd)
        _, status = os.waitpid(pid, 0)
    if result is not None:
        outcome, value = result
        if outcome == "ok":
            return value
        raise value
    if timed_out:
        raise TrialProcessDied(f"trial process killed after {timeout_s:g} s (the time limit) in "
                               f"stage {last_stage!r}", stage=last_stage, signal_name="SIGKILL",
                               exit_code=None)
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        name = signal.Signals(sig).name if sig in signal.valid_signals() else str(sig)
        raise TrialProcessDied(f"trial process killed by signal {name} ({sig}) in stage "
                               f"{last_stage!r}", stage=last_stage, signal_name=name,
                               exit_code=None)
    code = os.WEXITSTATUS(status) if os.WIFEXITED(status) else None
    raise TrialProcessDied(f"trial process exited with code {code} without a result in stage "
                           f"{last_stage!r}", stage=last_stage, signal_name=None, exit_code=code)
