"""Compiled kernels (numba, ``cache=True``): one signature each, and their compilation moved off a
run's critical path.

numba compiles a kernel on its first call and keeps it in its on-disk cache, keyed by the
argument types. A kernel called with a read-only array (a polars column) compiles once more, and
on a fresh install every kernel compiles in the run's only thread, one after the other.

So every kernel is called with C-contiguous, writable, aligned arrays (:func:`arg`): one
signature, declared by the kernel's module with :func:`register_kernel`. When numba's cache
lacks a kernel a run needs, :func:`warm` starts background processes that compile it into the
cache (on another core) while the run does its other work; the run waits for that process
(:func:`ready_for`) just before its first call, which then loads it from the cache. Compiled
code is the same either way, so the results are.

This module imports nothing from the package: a kernel module imports it to register, and the
background process imports the registered modules by name only.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Kernel", "KERNELS", "register_kernel", "arg", "in_cache", "is_cached", "warm", "job", "ready_for",
           "namespaces", "main"]

#: how long a run waits for a background compilation before compiling itself (s)
WAIT_S = 120.0
#: how often a waiting run looks for its kernel in numba's cache (s)
POLL_S = 0.05


@dataclass(frozen=True)
class Kernel:
    """A compiled kernel: the module that defines it (dotted name, imported by the background
    process), its dispatcher, and the builder of the one signature its callers give it (numba
    types, built on demand)."""

    module: str
    dispatcher: Callable
    signature: Callable[[], tuple]


#: name → the registered kernel
KERNELS: dict[str, Kernel] = {}


def register_kernel(name: str, module: str, dispatcher: Callable, signature: Callable[[], tuple]) -> None:
    """Declare kernel ``name`` (called at module level by the module ``module`` defining it)."""
    KERNELS[name] = Kernel(module, dispatcher, signature)


def arg(a, dtype=np.float64) -> np.ndarray:  # noqa: ANN001 - any array-like
    """``a`` as a kernel argument: C-contiguous, writable, aligned (a copy only when needed), so
    that each kernel has one signature (numba types a read-only array apart)."""
    return np.require(a, dtype, ("C", "W", "A"))


_jobs: dict[str, subprocess.Popen] = {}
_lock = threading.Lock()


def in_cache(disp, sig: tuple | None = None) -> bool:  # noqa: ANN001 - a numba dispatcher
    """Whether numba's on-disk cache holds ``disp`` compiled for ``sig`` (None: for any
    signature), read from the cache index without loading the code; False when that is not known
    (no cache location, or an internal of numba changed)."""
    try:
        index = disp._cache._cache_file._load_index()      # empty when stale or absent
        return bool(index) if sig is None else disp._cache._index_key(sig, disp.targetctx.codegen()) in index
    except Exception:
        return False


def is_cached(name: str) -> bool:
    """Whether kernel ``name`` is compiled in this process or numba's cache holds its signature."""
    k = KERNELS[name]
    if not hasattr(k.dispatcher, "signatures") or k.dispatcher.signatures:   # NUMBA_DISABLE_JIT: nothing to compile
        return True
    return in_cache(k.dispatcher, k.signature())


#: the directory holding the top-level package: the background process compiles these very sources
_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def namespaces(modules: Iterable[str]) -> list[str]:
    """Every package on the path of ``modules`` and of this module (parents first)."""
    out: list[str] = []
    for mod in (__name__, *modules):
        parts = mod.split(".")
        for n in range(1, len(parts)):
            pkg = ".".join(parts[:n])
            if pkg not in out:
                out.append(pkg)
    return out


#: the background process: the packages on the kernels' paths as bare namespaces, so that it
#: imports the kernels' modules only (numpy, numba, scipy), not the whole package (polars,
#: duckdb, plotly …, which the run's first kernel call would wait for)
_BOOT = """
import importlib, os, sys, types
root, pkgs, jit = sys.argv[1], sys.argv[2].split(","), sys.argv[3]
for name in pkgs:
    mod = types.ModuleType(name)
    mod.__path__ = [os.path.join(root, *name.split("."))]
    sys.modules[name] = mod
importlib.import_module(jit).main(sys.argv[4:])
"""


def _start(todo: Sequence[str], nice: bool) -> subprocess.Popen:
    """The background process compiling ``todo`` (in order)."""
    modules = [KERNELS[n].module for n in todo]
    specs = [f"{n}={m}" for n, m in zip(todo, modules)]
    return subprocess.Popen([sys.executable, "-c", _BOOT, _ROOT, ",".join(namespaces(modules)), __name__,
                             *(["--nice"] if nice else []), *specs],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def warm(groups: Sequence[Sequence[str]], names: Iterable[str]) -> list[str]:
    """Start compiling into numba's cache, in the background, the kernels of ``names`` it does
    not hold: one process per entry of ``groups`` (kernel names in the order a run first calls
    them; the first group at the run's priority, later ones niced). Returns those started. A
    failure there costs nothing: the run then compiles the kernel itself at its first call."""
    wanted = set(names)
    started: list[str] = []
    with _lock:
        for rank, group in enumerate(groups):
            todo = [n for n in group if n in wanted and n not in _jobs and not is_cached(n)]
            if not todo:
                continue
            try:
                job = _start(todo, nice=rank > 0)
            except (OSError, ValueError):   # no interpreter to start: the run compiles as before
                continue
            _jobs.update(dict.fromkeys(todo, job))
            started += todo
    return started


def job(name: str) -> subprocess.Popen | None:
    """The background process compiling ``name``, if one was started and not yet waited for."""
    return _jobs.get(name)


def ready_for(name: str, timeout_s: float = WAIT_S) -> None:
    """Wait for the background compilation of ``name`` (if any): the call that follows then
    loads the kernel from numba's cache instead of compiling it a second time. A process
    compiles its group in order; the wait ends when ``name`` is in the cache, not when the
    whole group is (a kernel does not wait for those compiled after it)."""
    with _lock:
        proc = _jobs.pop(name, None)
    end = time.monotonic() + timeout_s
    # past the timeout the run compiles the kernel itself; the process finishes on its own
    while proc is not None and proc.poll() is None and not is_cached(name) and time.monotonic() < end:
        time.sleep(POLL_S)


def main(argv: list[str]) -> None:
    """``[--nice] NAME=MODULE...``: import each MODULE (which registers kernel NAME) and compile
    the kernel into numba's cache (``--nice``: at a lower priority than the run that started
    it). :data:`_BOOT` calls it."""
    if argv[:1] == ["--nice"]:
        argv = argv[1:]
        try:
            os.nice(10)
        except (AttributeError, OSError):   # not POSIX, or not allowed: normal priority
            pass
    for spec in argv:
        name, module = spec.split("=", 1)
        importlib.import_module(module)
        k = KERNELS[name]
        k.dispatcher.compile(k.signature())
