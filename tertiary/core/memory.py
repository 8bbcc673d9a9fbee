"""How the process allocates memory: settings a command applies once, first thing, and the
release of freed memory a run asks for after each window.

They change the process (its environment, glibc's malloc), so they are explicit functions the
command line and the windows call, never side effects of importing the package.
"""

from __future__ import annotations

import ctypes
import functools
import os
import sys

#: jemalloc's setting appended to polars' own (``dirty_decay_ms:500,muzzy_decay_ms:1000``)
ALLOCATOR_CONF = "muzzy_decay_ms:0"
_M_ARENA_MAX = -8          # glibc's malloc.h


def configure_allocator() -> bool:
    """Make polars' allocator hand freed pages back to the kernel (True when set here).

    polars' allocator (jemalloc, prefix ``_rjem_``) purges a freed page after 0.5 s (dirty decay,
    polars' own setting) but then only advises the kernel it may take it (muzzy decay, 1 s): such
    pages stay in the resident set, so a stage stood on the last ones' pages. Muzzy decay 0 hands
    them back when purged, which lowers the peak and, with fewer page faults, the wall time
    (dirty decay 0 too would lower the peak further but is much slower). polars appends
    ``_RJEM_MALLOC_CONF`` to its own setting when it loads, and jemalloc reads the result once: so
    this must run before polars is first imported, and it leaves a value the environment sets."""
    if "polars" in sys.modules or "_RJEM_MALLOC_CONF" in os.environ:
        return False
    os.environ["_RJEM_MALLOC_CONF"] = ALLOCATOR_CONF
    return True


def one_malloc_arena() -> bool:
    """One glibc malloc arena for the process (True when set; False off glibc).

    Worker threads (the STCA curves predict two settings at a time) would each get an arena whose
    freed memory glibc keeps, raising the peak at no gain in speed. Polars and DuckDB allocate
    with their own allocators, untouched. Call it before any worker thread starts."""
    libc = _glibc()
    return bool(libc.mallopt(_M_ARENA_MAX, 1)) if libc is not None else False


def release_freed_memory() -> bool:
    """Hand glibc's freed pages back to the kernel (True when it released any; False when it had
    none to release, or off glibc).

    Between two windows most of a window's arrays are freed, but glibc returns to the kernel only
    the free memory at the top of its heap: pages freed below a block still in use stay in the
    resident set, and over a long run they add up. ``malloc_trim(0)`` releases every free page;
    it costs milliseconds, once per window."""
    libc = _glibc()
    return bool(libc.malloc_trim(0)) if libc is not None else False


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The C library when it is glibc (None elsewhere: macOS, musl), loaded once."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:                          # not glibc (macOS, musl)
        return None
    return libc if hasattr(libc, "malloc_trim") else None
