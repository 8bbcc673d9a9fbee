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
    shipped with their task (not hashed: ``pure=False``). ``record``: per call, the pieces'
    function, their number, the call's wall time on the client and each piece's time on its
    worker (s): what a model of more workers reads."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.record: list[dict] = []

    def __call__(self, fn: Callable[..., T], args: Sequence[tuple]) -> list[T]:
        args = list(args)
        if not args:
            return []
        t = time.perf_counter()
        futures = self.client.map(_timed, [fn] * len(args), *(list(col) for col in zip(*args)), pure=False)
        got = self.client.gather(futures)
        self.record.append({"piece": fn.__name__, "pieces": len(args), "wall_s": time.perf_counter() - t,
                            "task_s": [s for s, _ in got]})
        return [r for _, r in got]


def _timed(fn: Callable[..., T], *args: Any) -> tuple[float, T]:
    """(seconds, ``fn(*args)``): a piece timed where it runs."""
    t = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - t, out
