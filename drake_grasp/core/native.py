"""Keeps two copies of LLVM in one process apart: Mesa's (rendering) and triton's (torch).

The clash. Drake's VTK renderer draws headless through EGL; on a machine without a GPU,
Mesa's llvmpipe driver does the drawing, and Mesa's loader opens the driver with
``dlopen(RTLD_NOW | RTLD_GLOBAL)``, which puts the system's ``libLLVM-15.so`` into the
process's global symbol scope. A plain ``pip install torch`` brings the CUDA build with
``triton``, whose ``libtriton.so`` carries its own, newer LLVM with exported symbols.
torch imports triton lazily, the first time anything touches ``torch._dynamo`` - creating
any ``torch.optim`` optimizer does. If that happens after the first render, the dynamic
linker binds libtriton's calls to LLVM functions (e.g. ``llvm::cl::Option::addArgument``
in its static initializers) to Mesa's libLLVM-15 from the global scope, which then
works on libtriton's data laid out for another LLVM version: a segmentation fault while
loading libtriton (seen with torch 2.15.0 / triton 3.9.0 and drake 1.51.1, Debian 12's
Mesa 22.3). In the other order nothing clashes: Python loads extension modules with
``RTLD_LOCAL``, so libtriton's symbols never enter the global scope that Mesa's LLVM
resolves against.

The fix, in two parts:

- `load_llvm_users_first()` is called before this package creates a renderer: it loads
  libtriton (``import triton``, ~0.15 s, does not import torch) while Mesa's LLVM is not
  yet in the process, so every later order is safe - including a user's own torch code
  after an episode.
- When Mesa's LLVM is already loaded (a process that rendered through some other code
  first), it loads libtriton with ``RTLD_DEEPBIND``, so libtriton resolves its LLVM symbols
  inside itself first. Training code calls it before building an optimizer.

Where triton is not installed (torch's CPU builds), both are no-ops.
"""

from __future__ import annotations

import importlib.util
import os
import sys

# Shared libraries, loaded by Python extension modules, that carry a private LLVM.
_LLVM_CARRYING_MODULES = ("triton",)


def mesa_llvm_loaded() -> bool:
    """Whether a shared libLLVM (as Mesa's llvmpipe loads it) is mapped into this process."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            return any("/libLLVM" in line for line in f)
    except OSError:  # not Linux: Mesa's global-scope loading is a Linux/ELF matter
        return False


_GL_DRIVER_MARKS = ("_dri.so", "libEGL_mesa", "libEGL_nvidia", "libGLX_", "libnvidia-egl")


def gl_driver_loaded() -> bool:
    """Whether a GL driver (Mesa's llvmpipe or a GPU's EGL/GLX) is mapped into this
    process: it has rendered. A child forked from such a process must not render: the
    driver's threads (llvmpipe's rasterizers) and contexts do not survive the fork, and
    the child's first frame waits for them for ever."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            return any(mark in line for line in f for mark in _GL_DRIVER_MARKS)
    except OSError:  # pragma: no cover - not Linux: no /proc; assume it may have
        return True


def load_llvm_users_first() -> list[str]:
    """Loads the installed modules that carry their own LLVM (triton) before rendering.

    Safe to call any number of times, from any floor of the package; it imports nothing
    but those modules (not torch). Call it before the first EGL/VTK render of a process.

    Returns:
        The modules loaded by this call (empty when none is installed or all are loaded).
    """
    loaded = []
    for name in _LLVM_CARRYING_MODULES:
        if name in sys.modules or importlib.util.find_spec(name) is None:
            continue
        deepbind = getattr(os, "RTLD_DEEPBIND", 0) if mesa_llvm_loaded() else 0
        flags = sys.getdlopenflags()
        if deepbind:
            # Mesa's LLVM is already global: make libtriton look up its own symbols first.
            sys.setdlopenflags(flags | deepbind)
        try:
            __import__(name)
        except Exception:  # noqa: BLE001 - a broken optional package must not stop rendering
            continue
        finally:
            sys.setdlopenflags(flags)
        loaded.append(name)
    return loaded
