"""The fusion methods behind one registry.

Each method is a frozen :class:`FusionMethod` description registered by name (:func:`register`)
by the module of its family (:mod:`tertiary.stages.fusion.methods`); :func:`run_methods`
dispatches through it. The method lists callers use (``METHODS``, ``ALL_METHODS``, …) are views
of the registry, in the order of :attr:`FusionMethod.rank` (:func:`registered`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tertiary.stages.fusion.base import F, Fused, Ix, Layout, blocks, inv_spd
from tertiary.stages.fusion.config import FusionConfig

__all__ = [
    "Block", "BlockFuse", "FusionMethod", "PlotWeights", "REGISTRY", "RunInputs", "RunWeights", "check_methods",
    "register", "registered", "run_methods",
]


@dataclass(frozen=True)
class RunInputs:
    """What the methods read over all rows of one call: the per-row arrays ``a`` (``x``, ``cov``,
    ``res``, ``res_var``, ``fresh``, ``nominal_var``; ``lam`` and ``u``, ``a_pred``, ``dvar`` when
    a method needs them), the group layout, the parameters, and ``d_fixed`` (the D_n of
    ``aposteriori_seed``, computed on demand because it needs the radars)."""

    a: Mapping[str, NDArray]
    lay: Layout
    cfg: FusionConfig
    d_fixed: Callable[[], F]


@dataclass(frozen=True)
class Block:
    """A run of whole groups (rows ``rows`` of the call, group-local ``starts``) with its states and
    covariances, their inverses when a method shares them (``cov_inv``), and the method's
    whole-call weights restricted to the block (``weights``, recursive methods only)."""

    x: F
    cov: F
    starts: Ix
    rows: slice
    run: RunInputs
    cov_inv: F | None = None
    weights: F | None = None

    def col(self, name: str) -> NDArray:
        """The block's rows of the per-row input ``name``."""
        return self.run.a[name][self.rows]


#: the fusion of one block: per-group state and covariance, per-row weights
BlockFuse = Callable[[Block], Fused]
#: a recursion over all rows of a call, given the weights carried from the previous window
RunWeights = Callable[[RunInputs, "F | None"], F]
#: the weights of the plot-level measurement: (per-row inputs, layout, fresh rows, their plot
#: covariances (k, 3, 3), the fresh rows' group starts) -> weights of the fresh rows
PlotWeights = Callable[[Mapping[str, NDArray], Layout, Ix, F, Ix], F]


@dataclass(frozen=True)
class FusionMethod:
    """One fusion method.

    * ``name``: as selected by the user and written in the ``method`` column;
    * ``family``: the module that implements it;
    * ``fuse``: the block kernel;
    * ``rank``: position in the method lists (the order of the fused table's blocks by default);
    * ``default``: in ``METHODS`` (else selectable by name only: ``EXTRA_METHODS``);
    * ``weights``: the recursion over all rows for the a-posteriori methods, whose weights are
      carried across windows (:attr:`recursive`); ``per_axis``: those weights are (n, 3);
    * ``info_plots``: the plot-level measurement is the inverse-covariance combination of the
      plots; ``plot_weights``: its weights when they are not the method's own;
    * ``shares_cov_inv``: reads the block's C_n⁻¹ (computed once for all such methods);
    * ``line_of_sight``: needs each radar's line of sight (``u``, ``a_pred``, ``dvar``);
    * ``nis_inflation``: needs the per-row NIS inflation ``lam``.
    """

    name: str
    family: str
    fuse: BlockFuse
    rank: int
    default: bool = True
    weights: RunWeights | None = None
    per_axis: bool = False
    info_plots: bool = False
    plot_weights: PlotWeights | None = None
    shares_cov_inv: bool = False
    line_of_sight: bool = False
    nis_inflation: bool = False

    @property
    def recursive(self) -> bool:
        """Whether the weights are a recursion carried across windows."""
        return self.weights is not None


REGISTRY: dict[str, FusionMethod] = {}


def register(method: FusionMethod) -> FusionMethod:
    """Add ``method`` to :data:`REGISTRY` under its name."""
    if method.name in REGISTRY:
        raise ValueError(f"fusion method {method.name!r} registered twice")
    REGISTRY[method.name] = method
    return method


def registered(keep: Callable[[FusionMethod], bool] = lambda m: True) -> tuple[str, ...]:
    """The names of the registered methods that ``keep`` accepts, by rank."""
    return tuple(m.name for m in sorted(REGISTRY.values(), key=lambda m: m.rank) if keep(m))


def check_methods(methods: Sequence[str]) -> list[str]:
    """``methods`` as a list without repeats; ValueError for a name not registered."""
    if isinstance(methods, str):
        methods = [methods]
    known = registered()
    bad = [m for m in methods if m not in REGISTRY]
    if bad:
        raise ValueError(f"unknown fusion method(s) {bad}; choose from {', '.join(known)}")
    return list(dict.fromkeys(methods))


def run_methods(methods: list[str], run: RunInputs, b0: dict[str, F] | None = None
                ) -> tuple[F, F, F, dict[str, F]]:
    """Every method over all groups: states (M, G, 6), covariances (M, G, 6, 6) and weights
    (M, n), M methods in the order given, and the per-axis weights (n, 3) of the methods that
    have them. The a-posteriori recursions run once over every row (per-row scalars); the
    mixing and all per-group linear algebra run block by block, all methods in one pass so that
    information fusion and CI share the block's C_n⁻¹, written straight into the outputs.
    Memory is bounded by the block, not by the dataset (stacked 6×6 temporaries over all rows
    reached gigabytes). ``b0``: per recursive method, the weights carried from the previous
    window (NaN: none)."""
    specs = [REGISTRY[m] for m in methods]
    x, cov, lay = run.a["x"], run.a["cov"], run.lay
    b0 = b0 or {}
    n_groups = len(lay.starts)
    xs = np.empty((len(specs), n_groups, 6))
    covs = np.empty((len(specs), n_groups, 6, 6))
    ws = np.empty((len(specs), len(x)))
    w = {s.name: s.weights(run, b0.get(s.name)) for s in specs if s.weights is not None}
    shared_inv = any(s.shares_cov_inv for s in specs)
    for r, st in blocks(lay.starts, len(x)):
        g0 = int(np.searchsorted(lay.starts, r.start))
        g = slice(g0, g0 + len(st))
        xb, cb = x[r], cov[r]
        cinv = inv_spd(cb) if shared_inv else None
        for i, s in enumerate(specs):
            blk = Block(xb, cb, st, r, run, cinv, w[s.name][r] if s.name in w else None)
            xs[i, g], covs[i, g], ws[i, r] = s.fuse(blk)
    return xs, covs, ws, {m: v for m, v in w.items() if REGISTRY[m].per_axis}
