"""The pipeline's compiled kernels (numba, ``cache=True``): one signature each, and a fresh
install's compilation moved off the run's critical path (issue 18).

numba compiles a kernel on its first call and keeps it in its on-disk cache, keyed by the
argument types. Two things made a fresh install's first ``tertiary run`` ~18 s slower than the
next one on the 2-core machine: the altitude filter compiled twice (once more for a read-only
argument: an array taken from a polars column), and the three kernels — the altitude filter
(fusion and centralised reference) and the IMM predict and update (tracker) — compiled one
after the other in the run's only thread, ~4 s each.

So every kernel is called with C-contiguous, writable, aligned arrays (:func:`arg`): one
signature, known in advance (:data:`KERNELS`). When numba's cache lacks one the run needs,
:func:`warm` starts background processes that compile them into the cache (on the other core)
while the run reads, validates, aligns and associates; the run waits for that
process (:func:`ready_for`) just before its first call, which then loads it from the cache.
Compiled code is the same either way, so the results are.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable

import numpy as np

__all__ = ["KERNELS", "arg", "in_cache", "is_cached", "warm", "ready_for", "kernels_for"]

#: how long a run waits for a background compilation before compiling itself (s)
WAIT_S = 120.0
#: how often a waiting run looks for its kernel in numba's cache (s)
POLL_S = 0.05


def arg(a, dtype=np.float64) -> np.ndarray:
    """``a`` as a kernel argument: C-contiguous, writable, aligned (a copy only when needed), so
    that each kernel has one signature (numba types a read-only array apart)."""
    return np.require(a, dtype, ("C", "W", "A"))


def _altitude():  # noqa: ANN202 - (dispatcher, signature)
    from numba import types as t

    from tertiary.stages.tracking.altitude_kernel import _filter
    f1, i1, b1 = (t.Array(d, 1, "C") for d in (t.float64, t.int64, t.boolean))
    f2, f3 = t.Array(t.float64, 2, "C"), t.Array(t.float64, 3, "C")
    return _filter, (f1, f1, f1, i1, i1, i1, f1, f1, t.float64, t.float64, t.int64, t.float64, t.float64,
                     f3, f2, f1, b1, b1, i1, i1, f2, b1, f2, b1, b1)


def _imm_predict():  # noqa: ANN202
    from numba import types as t

    from tertiary.stages.tracking.filters.imm import _imm_predict_nb
    f1, f2, f3, f4 = (t.Array(t.float64, n, "C") for n in (1, 2, 3, 4))
    return _imm_predict_nb(), (f3, f4, f2, f1, f1, f2, t.float64, f2, f3, t.float64)


def _imm_update():  # noqa: ANN202
    from numba import types as t

    from tertiary.stages.tracking.filters.imm import _imm_update_nb
    f1, f2, f3, f4 = (t.Array(t.float64, n, "C") for n in (1, 2, 3, 4))
    return _imm_update_nb(), (f3, f4, f2, f2, f3, f2, f3, f1, t.Array(t.boolean, 1, "C"), t.float64)


def _pcrb():  # noqa: ANN202
    from numba import types as t

    from tertiary.evaluation.bound_kernel import pcrb_singer9
    f2, f3 = t.Array(t.float64, 2, "C"), t.Array(t.float64, 3, "C")
    i1, b1 = t.Array(t.int64, 1, "C"), t.Array(t.boolean, 1, "C")
    return pcrb_singer9, (f3, f3, f3, b1, i1, i1, f2, i1, f2)


#: name → (dispatcher, the one signature its callers give it)
KERNELS: dict[str, Callable[[], tuple]] = {"altitude": _altitude, "imm_predict": _imm_predict,
                                            "imm_update": _imm_update, "pcrb": _pcrb}

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
    disp, sig = KERNELS[name]()
    if not hasattr(disp, "signatures") or disp.signatures:   # NUMBA_DISABLE_JIT: nothing to compile
        return True
    return in_cache(disp, sig)


def kernels_for(filters: Iterable[str], bound: bool = False) -> list[str]:
    """The kernels a run with tracker ``filters`` calls: the altitude filter (fusion and the
    centralised reference) always, the IMM's when a filter is the compiled IMM, and with
    ``bound`` (the run has a truth to evaluate against) the Cramér–Rao bound's recursion."""
    from tertiary.stages.tracking.filters import make_filter
    from tertiary.stages.tracking.filters.imm import IMMFilter
    names = ["altitude"]
    for f in filters:
        try:
            flt = make_filter(f)
        except Exception:  # an unknown name fails later, with the tracker's message
            continue
        if isinstance(flt, IMMFilter) and flt._q_iso is not None:
            names += ["imm_predict", "imm_update"]
            break
    return names + (["pcrb"] if bound else [])


#: kernels compiled together, in the order a run first calls them: the first group at the run's
#: priority (the fusion waits for it within seconds), later ones niced (the tracker's come later,
#: the bound's last: in a process of its own it took the core from the tracker's on a fresh
#: install, whose first run went from 3.1 to 5.3 s over a warm one)
GROUPS: tuple[tuple[str, ...], ...] = (("altitude",), ("imm_predict", "imm_update", "pcrb"))


#: this package's directory: the background process compiles these very sources
_PKG = os.path.dirname(os.path.abspath(__file__))

#: the background process: this package and its ``filters`` subpackage as bare namespaces, so
#: that it imports the kernels' modules only (numpy, numba, scipy.linalg), not the whole
#: package (polars, duckdb, plotly …: ~1.3 s that the run's first fusion would wait for)
_BOOT = """
import os, sys, types
pkg = sys.argv[1]
for name, path in (("tertiary", pkg), ("tertiary.stages.tracking.filters", os.path.join(pkg, "filters"))):
    mod = types.ModuleType(name)
    mod.__path__ = [path]
    sys.modules[name] = mod
from tertiary.runtime.warmup import main
main(sys.argv[2:])
"""


def warm(names: Iterable[str]) -> list[str]:
    """Start compiling into numba's cache, in the background (one process per :data:`GROUPS`
    entry), the kernels of ``names`` it does not hold; returns those started. A failure there
    costs nothing: the run then compiles the kernel itself at its first call, as it would have."""
    wanted = set(names)
    started: list[str] = []
    with _lock:
        for rank, group in enumerate(GROUPS):
            todo = [n for n in group if n in wanted and n not in _jobs and not is_cached(n)]
            if not todo:
                continue
            try:
                job = subprocess.Popen([sys.executable, "-c", _BOOT, _PKG, *(["--nice"] if rank else []), *todo],
                                       stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                       stderr=subprocess.DEVNULL)
            except (OSError, ValueError):   # no interpreter to start: the run compiles as before
                continue
            _jobs.update(dict.fromkeys(todo, job))
            started += todo
    return started


def ready_for(name: str, timeout_s: float = WAIT_S) -> None:
    """Wait for the background compilation of ``name`` (if any): the call that follows then
    loads the kernel from numba's cache instead of compiling it a second time. A process
    compiles its group in order; the wait ends when ``name`` is in the cache, not when the
    whole group is (the tracker does not wait for the bound's kernel compiled after its own)."""
    with _lock:
        job = _jobs.pop(name, None)
    end = time.monotonic() + timeout_s
    # past the timeout the run compiles the kernel itself; the process finishes on its own
    while job is not None and job.poll() is None and not is_cached(name) and time.monotonic() < end:
        time.sleep(POLL_S)


def _compile(name: str) -> None:
    disp, sig = KERNELS[name]()
    disp.compile(sig)


def main(argv: list[str]) -> None:
    """``[--nice] NAME...``: compile the kernels into numba's cache (``--nice``: at a lower
    priority than the run that started it). :data:`_BOOT` calls it; so does
    ``python -m tertiary.runtime.warmup``."""
    if argv[:1] == ["--nice"]:
        argv = argv[1:]
        try:
            os.nice(10)
        except (AttributeError, OSError):   # not POSIX, or not allowed: normal priority
            pass
    for name in argv:
        _compile(name)


if __name__ == "__main__":
    main(sys.argv[1:])
