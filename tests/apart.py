"""A fanout (:mod:`tertiary.runtime.fanout`) that runs each piece as a cluster's worker would:
from pickled arguments, in an order of its own (last first), its results returned in order."""

from __future__ import annotations

import pickle
from collections.abc import Callable, Sequence
from typing import Any


class Apart:
    """A fanout that counts its pieces by function name (``pieces``)."""

    def __init__(self) -> None:
        self.pieces: dict[str, int] = {}

    def __call__(self, fn: Callable[..., Any], args: Sequence[tuple]) -> list[Any]:
        shipped = [pickle.loads(pickle.dumps((fn, a))) for a in args]
        self.pieces[fn.__name__] = self.pieces.get(fn.__name__, 0) + len(shipped)
        done = {i: f(*a) for i, (f, a) in reversed(list(enumerate(shipped)))}
        return [done[i] for i in range(len(shipped))]
