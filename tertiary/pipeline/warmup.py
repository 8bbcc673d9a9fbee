"""The pipeline's compiled kernels and their background warm-up (machinery: :mod:`tertiary.core.jit`):
which kernels a run calls, and in which groups they are compiled while the run reads, validates,
aligns and associates. It imports the kernels' modules, which registers them."""

from __future__ import annotations

from collections.abc import Iterable

from tertiary.core import jit
from tertiary.evaluation import bound_kernel  # noqa: F401  (registers "pcrb")
from tertiary.stages.tracking import altitude_kernel  # noqa: F401  (registers "altitude")
from tertiary.filters import make_filter
from tertiary.filters.imm import IMMFilter

__all__ = ["GROUPS", "kernels_for", "warm_kernels"]

#: kernels compiled together, in the order a run first calls them: the first group at the run's
#: priority (the fusion waits for it within seconds), later ones niced (the tracker's come later,
#: the bound's last: in a process of its own it took the core from the tracker's on a fresh
#: install)
GROUPS: tuple[tuple[str, ...], ...] = (("altitude",),
                                       ("imm_predict", "imm_output", "imm_update", "imm_velocity", "pcrb"))


def kernels_for(filters: Iterable[str], bound: bool = False) -> list[str]:
    """The kernels a run with tracker ``filters`` calls: the altitude filter (fusion and the
    centralised reference) always, the IMM's when a filter is the compiled IMM, and with
    ``bound`` (the run has a truth to evaluate against) the Cramér–Rao bound's recursion."""
    names = ["altitude"]
    for f in filters:
        try:
            flt = make_filter(f)
        except Exception:  # an unknown name fails later, with the tracker's message
            continue
        if isinstance(flt, IMMFilter) and flt.compiled:
            names += ["imm_predict", "imm_output", "imm_update", "imm_velocity"]
            break
    return names + (["pcrb"] if bound else [])


def warm_kernels(names: Iterable[str]) -> list[str]:
    """Start compiling, in the background, the kernels of ``names`` that numba's cache lacks
    (one process per :data:`GROUPS` entry); returns those started."""
    return jit.warm(GROUPS, names)
