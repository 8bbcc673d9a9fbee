"""Where a whole-run stage's independent pieces run: one after another in this process (a local
run), or as tasks of a Dask cluster (the finalize of a distributed run, whose workers would
otherwise wait while the client computes alone).

A :data:`Fanout` takes a function and one argument tuple per piece and yields the pieces'
results in the order of the tuples, so a stage that merges them in that order gets the same
result whichever runs them. The pieces' functions and arguments must be picklable (top-level
functions, paths rather than open scans) for a cluster to run them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, TypeVar

__all__ = ["Fanout", "serial", "DaskFanout"]

T = TypeVar("T")

#: ``fanout(fn, [args, …])`` → ``fn(*args)`` of each tuple, in order
Fanout = Callable[[Callable[..., T], Sequence[tuple]], Iterable[T]]


def serial(fn: Callable[..., T], args: Sequence[tuple]) -> Iterator[T]:
    """Each piece in turn, in this process, computed as it is read (a stage that merges as it
    goes holds one piece at a time)."""
    return (fn(*a) for a in args)


class DaskFanout:
    """Each piece a task of ``client``'s cluster; the results gathered in order. Arguments are
    shipped with their task (not hashed: ``pure=False``). A call of one piece runs it here: the
    client would only wait for it, and shipping it costs more than a small piece (a short
    recording's pictures). ``record``: per call, the pieces' function, their number, where they
    ran (``workers``, ``client``), the call's wall time and each piece's own time (s): what a
    model of more workers reads."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.record: list[dict] = []

    def __call__(self, fn: Callable[..., T], args: Sequence[tuple]) -> list[T]:
        args = list(args)
        if not args:
            return []
        t = time.perf_counter()
        if len(args) == 1:
            got, where = [_timed(fn, *args[0])], "client"
        else:
            futures = self.client.map(_timed, [fn] * len(args), *(list(col) for col in zip(*args)), pure=False)
            got, where = self.client.gather(futures), "workers"
        self.record.append({"piece": fn.__name__, "pieces": len(args), "where": where,
                            "wall_s": time.perf_counter() - t, "task_s": [s for s, _ in got]})
        return [r for _, r in got]


def _timed(fn: Callable[..., T], *args: Any) -> tuple[float, T]:
    """(seconds, ``fn(*args)``): a piece timed where it runs."""
    t = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - t, out
