"""The secondary tracker's epoch loop over one filter's bank of objects: prediction, gating and
assignment of the confirmed tracks, initiation (three-scan or M-of-N), one filter update, track
deletion, and the emitted rows. The rules are those of :mod:`tertiary.stages.tracking.tracker`
(steps 1 to 6)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core.units import STATE, US
from tertiary.stages.tracking.altitude import ALT_COLUMNS, AltState, predict as alt_predict, update2 as alt_update
from tertiary.stages.tracking.altitude import update_rate as alt_update_rate
from tertiary.stages.tracking.config import TRACK_COLUMNS, TrackerConfig
from tertiary.filters.base import State, TrackFilter, concat, full_cov, size, take
from tertiary.stages.tracking.gating import (PlotIndex, Plots, altitude_ok, assign, identity_ok, likelihood_cost,
                                             tracking_pairs, velocity_covariance, vertical_ok)

__all__ = ["Bank", "Emitted", "track_batch"]

_TENT, _HYP, _CONF = 0, 1, 2          # object kinds: tentative (stage 1 / M-of-N), scan-2 hypothesis, confirmed


# Every object (tentative, hypothesis or confirmed track) is a row of two packed arrays, so the
# bookkeeping follows the filter state with two fancy-indexing operations per selection.
# float columns:
# _T: time of the filter state (the last measurement's time, epoch − age); _TA: time of the
# altitude filter (updated with the plot's vertical channel, which is at the epoch)
_T, _P1, _T1, _RZ1, _P2, _T2, _RZ2 = 0, slice(1, 4), 4, 5, slice(6, 9), 9, 10
_ALT = slice(11, 16)                  # altitude filter h, ḣ, P_hh, P_hḣ, P_ḣḣ (NaN: none yet)
_TA = 16
_NF = 17
# int columns: run index, kind, track id (0 until confirmed), consecutive misses, M-of-N hits
# and scans, uid of the scan-1 plot, uid of the scan-2 plot
_RUN, _KIND, _ID, _MISS, _HITS, _SCANS, _ROOT, _UID2, _IDENT = range(9)
_NI = 9


@dataclass
class _Objects:
    f: NDArray      # (B, _NF) float64
    i: NDArray      # (B, _NI) int64

    @staticmethod
    def empty() -> "_Objects":
        return _Objects(np.zeros((0, _NF)), np.zeros((0, _NI), np.int64))

    def __len__(self) -> int:
        return len(self.i)

    def take(self, idx: NDArray) -> "_Objects":
        return _Objects(self.f[idx], self.i[idx])

    @staticmethod
    def concat(*objs: "_Objects") -> "_Objects":
        objs = tuple(o for o in objs if len(o))
        if not objs:
            return _Objects.empty()
        if len(objs) == 1:
            return objs[0]
        return _Objects(np.concatenate([o.f for o in objs]), np.concatenate([o.i for o in objs]))

    @staticmethod
    def new(run: NDArray, t: float, z: NDArray, rz: NDArray, uid: NDArray, alt: NDArray,
            ident: NDArray | None = None) -> "_Objects":
        n = len(run)
        f = np.zeros((n, _NF))
        f[:, _ALT] = alt
        f[:, _T] = f[:, _T1] = f[:, _TA] = t
        f[:, _P1] = z
        f[:, _RZ1] = rz
        i = np.zeros((n, _NI), np.int64)
        i[:, _RUN] = run
        i[:, _KIND] = _TENT
        i[:, _HITS] = i[:, _SCANS] = 1
        i[:, _ROOT] = uid
        i[:, _UID2] = -1
        i[:, _IDENT] = -1 if ident is None else ident
        return _Objects(f, i)


def _alt_step(f: NDArray, t: float, plot_alt: NDArray, mask: NDArray, q: float) -> NDArray:
    """The altitude filter of objects ``f`` (rows of _Objects.f) predicted to ``t`` and updated
    with their plots' vertical channel where ``mask`` and the plot has one; objects without an
    estimate start from the plot's. Returns the new (n, 5) block."""
    cur = AltState(*(f[:, _ALT.start + i] for i in range(5)))
    pred = alt_predict(cur, t - f[:, _TA], q)
    meas = AltState(*(plot_alt[:, i] for i in range(5)))
    have_m = mask & np.isfinite(plot_alt).all(axis=1)
    have_t = np.isfinite(pred.h)
    with np.errstate(invalid="ignore", divide="ignore"):
        upd = alt_update(pred, meas)
    cols = []
    for name in ("h", "r", "phh", "phr", "prr"):
        p, u, m = getattr(pred, name), getattr(upd, name), getattr(meas, name)
        cols.append(np.where(have_m, np.where(have_t, u, m), p))
    return np.column_stack(cols) if len(f) else np.zeros((0, 5))


def _alt_rate_step(alt: NDArray, rate: NDArray, mask: NDArray, cfg: TrackerConfig, dt: NDArray) -> NDArray:
    """The (n, 5) altitude filter block ``alt`` updated with the downlinked vertical rates
    ``rate`` where ``mask``, the filter has an estimate and the NIS is within the gate, its
    variance grown by the vertical acceleration allowed over the ``dt`` since the last update.
    A rate outside the plain gate but inside the grown one is the onset of a climb or a
    level-off, which the constant-rate filter cannot know: its rate variance takes that
    allowance before the update, so that the rate follows the register at once."""
    s = AltState(*(alt[:, i] for i in range(5)))
    var = np.full(len(alt), cfg.vertical_rate_sigma_mps ** 2)
    allow = (cfg.vertical_accel_mps2 * np.maximum(dt, 0.0)) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        d2 = (rate - s.r) ** 2
        onset = d2 > cfg.vertical_rate_gate * (s.prr + var)
        use = mask & np.isfinite(rate) & np.isfinite(s.h) & (d2 <= cfg.vertical_rate_gate * (s.prr + var + allow))
        prior = AltState(s.h, s.r, s.phh, s.phr, np.where(onset, s.prr + allow, s.prr))
        upd, _, _ = alt_update_rate(prior, rate, var)
    if not use.any():
        return alt
    return np.where(use[:, None], np.column_stack([upd.h, upd.r, upd.phh, upd.phr, upd.prr]), alt)


def _alt_at(f: NDArray, t: float, q: float) -> NDArray:
    """The objects' altitude filter predicted to ``t``: (n, 2) altitude and its variance (NaN:
    no altitude yet)."""
    pred = alt_predict(AltState(*(f[:, _ALT.start + i] for i in range(5))), t - f[:, _TA], q)
    return np.column_stack([pred.h, pred.phh]) if len(f) else np.zeros((0, 2))


def _take_state(state: State, idx: NDArray, n: int) -> State:
    """``take`` that skips the copy when ``idx`` selects every track in order."""
    if len(idx) == n and (n == 0 or (idx[0] == 0 and (n == 1 or bool((np.diff(idx) == 1).all())))):
        return state
    return take(state, idx)


def _join_states(*states: State) -> State:
    out: State = {}
    for s_ in states:
        if s_ and size(s_):
            out = concat(out, s_)
    return out


# --------------------------------------------------------------------------- gating


def _annulus_pairs(plots: Plots, free: NDArray, objs: _Objects, t: float,
                   cfg: TrackerConfig) -> tuple[NDArray, NDArray]:
    """(object, plot) pairs with the plot in the annulus S₁ around the object's last plot:
    v_min·T ≤ horizontal distance ≤ v_max·T, T = t − t₁ (1.1), a plausible height change and
    no other Mode S address than the object's (:func:`identity_ok`)."""
    if len(objs) == 0 or not free.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    p1, dt = objs.f[:, _P1], t - objs.f[:, _T1]
    o, p = plots.window(objs.i[:, _RUN], p1[:, 0], cfg.v_max_mps * dt)
    keep = free[p]
    o, p = o[keep], p[keep]
    dh = np.hypot(plots.z[p, 0] - p1[o, 0], plots.z[p, 1] - p1[o, 1])
    ok = ((dh >= cfg.v_min_mps * dt[o]) & (dh <= cfg.v_max_mps * dt[o])
          & vertical_ok(plots.z[p, 2] - p1[o, 2], objs.f[o, _RZ1], plots.r[p, 2], cfg)
          & identity_ok(objs.i[o, _IDENT], plots.ident[p], cfg))
    if cfg.alt_gate_m is not None:
        ok &= altitude_ok(_alt_at(objs.f, t, cfg.altitude.q_m2ps3)[o], plots.alt[p], cfg)
    return o[ok], p[ok]


def _confirm_pairs(plots: Plots, free: NDArray, hyp: _Objects, t: float,
                   cfg: TrackerConfig) -> tuple[NDArray, NDArray, NDArray]:
    """(hypothesis, plot, cost) of plots inside the scan-3 circle S₂ around
    x̂₃ = x₂ + (x₂ − x₁)·(t − t₂)/(t₂ − t₁) and of no other Mode S address than the hypothesis';
    cost = (d_h/R_S₂)² + (Δz/tolerance)²."""
    if len(hyp) == 0 or not free.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    p1, p2 = hyp.f[:, _P1], hyp.f[:, _P2]
    ratio = (t - hyp.f[:, _T2]) / np.maximum(hyp.f[:, _T2] - hyp.f[:, _T1], 1e-9)
    x3 = p2 + (p2 - p1) * ratio[:, None]
    o, p = plots.window(hyp.i[:, _RUN], x3[:, 0], np.full(len(hyp), cfg.confirm_gate_m))
    keep = free[p]
    o, p = o[keep], p[keep]
    dz = plots.z[p, 2] - x3[o, 2]
    dh2 = (plots.z[p, 0] - x3[o, 0]) ** 2 + (plots.z[p, 1] - x3[o, 1]) ** 2
    tol = cfg.gate_sigma * np.sqrt(hyp.f[o, _RZ2] + plots.r[p, 2]) + cfg.gate_min_m
    ok = (np.abs(dz) <= tol) & (dh2 <= cfg.confirm_gate_m ** 2) & identity_ok(hyp.i[o, _IDENT], plots.ident[p], cfg)
    if cfg.alt_gate_m is not None:
        ok &= altitude_ok(_alt_at(hyp.f, t, cfg.altitude.q_m2ps3)[o], plots.alt[p], cfg)
    return o[ok], p[ok], dh2[ok] / cfg.confirm_gate_m ** 2 + (dz[ok] / tol[ok]) ** 2


# --------------------------------------------------------------------------- assignment


class Emitted:
    """Output rows accumulated epoch by epoch."""

    def __init__(self) -> None:
        self.parts: dict[str, list[NDArray]] = {k: [] for k in
                                                ("run", "epoch", "track_id", "x", "var", "cov", "nu", "nis", "upd",
                                                 "tid", "alt")}
        self.probs: list[NDArray | None] = []

    def add(self, **arrays) -> None:
        probs = arrays.pop("probs")
        for k, v in arrays.items():
            self.parts[k].append(v)
        self.probs.append(probs)

    def _probs(self, n: int) -> NDArray | None:
        """Model probabilities of every row (NaN-padded to the widest), None if no filter has any."""
        if all(pr is None for pr in self.probs):
            return None
        width = max(pr.shape[1] for pr in self.probs if pr is not None)
        probs = np.full((n, width), np.nan)
        at = 0
        for pr, part in zip(self.probs, self.parts["run"]):
            if pr is not None:
                probs[at:at + len(part), :pr.shape[1]] = pr
            at += len(part)
        return probs

    def frame(self, runs: NDArray, filt_name: str, methods: list[str], run_method: NDArray) -> pl.DataFrame:
        """The rows as a ``tracks`` table; batch run index j is run ``runs[j]`` of fusion method
        ``methods[run_method[j]]``. Sorted by (batch run, epoch, track_id)."""
        if not self.parts["run"] or sum(len(a) for a in self.parts["run"]) == 0:
            return pl.DataFrame(schema=TRACK_COLUMNS)
        c = {k: np.concatenate(v, axis=0) for k, v in self.parts.items()}
        n = len(c["run"])
        probs = self._probs(n)
        # sort by (run, epoch, track_id) in numpy (unique keys, runs sorted): cheaper than
        # sorting the wide polars frame
        order = np.lexsort((c["track_id"], c["epoch"], c["run"]))
        c = {k: v[order] for k, v in c.items()}
        upd = c["upd"]
        nu = pl.Series("innovation", c["nu"]).cast(pl.List(pl.Float64))
        if probs is not None:
            probs = probs[order]
            has = ~np.isnan(probs).all(axis=1)
            model_probs = pl.Series("model_probs", probs).cast(pl.List(pl.Float64))
        else:
            has = np.zeros(n, bool)
            model_probs = pl.Series("model_probs", [None] * n, dtype=pl.List(pl.Float64))
        frame = pl.DataFrame({
            "run": runs[c["run"]].astype(np.uint32),
            "epoch": pl.Series(c["epoch"]).cast(pl.Datetime("us")).dt.replace_time_zone("UTC"),
            "track_id": c["track_id"].astype(np.uint64),
            # constant and two-valued strings built by polars: numpy object/str arrays convert slowly
            "filter": pl.repeat(filt_name, n, dtype=pl.String, eager=True),
            "method": (pl.repeat(methods[0], n, dtype=pl.String, eager=True) if len(methods) == 1 else
                       pl.Series(methods, dtype=pl.String).gather(run_method[c["run"]])),
            **{col: c["x"][:, i] for i, col in enumerate(STATE)},
            "cov_diag": c["var"],
            "cov": c["cov"],
            # AltState order h, ḣ, P_hh, P_hḣ, P_ḣḣ → ALT_COLUMNS
            **{col: c["alt"][:, j] for col, j in zip(ALT_COLUMNS, (0, 1, 2, 4, 3))},
            "innovation": nu,
            "nis": c["nis"],
            "model_probs": model_probs,
            "plot_target_id": c["tid"],
            "__upd": upd,
            "__has_probs": has,
        })
        upd_col = pl.col("__upd")
        frame = frame.with_columns(
            pl.when(upd_col).then(pl.col("innovation")).alias("innovation"),
            pl.when(upd_col).then(pl.col("nis")).alias("nis"),
            pl.when(upd_col).then(pl.col("plot_target_id")).alias("plot_target_id"),
            pl.when(pl.col("__has_probs")).then(pl.col("model_probs")).alias("model_probs"),
            pl.when(upd_col).then(pl.lit("confirmed")).otherwise(pl.lit("coasting")).alias("status"),
        )
        frame = frame.with_columns(pl.col(list(ALT_COLUMNS)).fill_nan(None))
        return frame.select(list(TRACK_COLUMNS)).cast(TRACK_COLUMNS)


def track_batch(ix: "PlotIndex", filt: TrackFilter, cfg: TrackerConfig, bank: "Bank", n_runs: int,
                 origin_us: int) -> tuple["Emitted", "Bank"]:
    """The tracker's epoch loop over the plots of one window (``ix``, batch run indices
    0 ≤ j < ``n_runs``; batch runs never interact), starting from ``bank`` (never modified).
    Object times are float seconds since ``origin_us``. Returns the emitted rows and the bank
    at the end of the window."""
    secs = (ix.epochs - origin_us) / US
    state: State = bank.filt_state
    objs = _Objects(bank.f, bank.i)
    next_id = np.r_[bank.next_id, np.ones(n_runs - len(bank.next_id), np.int64)]
    emitted = Emitted()
    three = cfg.initiation == "three_scan"
    empty = np.zeros(0, np.int64)

    for k, t in enumerate(secs):
        plots = ix.epoch(k)
        n_plot = len(plots.run)

        # --- predict the objects of the runs that have plots now
        if n_runs == 1:
            act, idle = np.arange(len(objs)), empty
        else:
            run_on = np.zeros(n_runs, bool)
            run_on[plots.run] = True
            on = run_on[objs.i[:, _RUN]]
            act, idle = np.flatnonzero(on), np.flatnonzero(~on)
        m = objs.take(act) if len(idle) else objs
        prev = _take_state(state, act, len(objs))
        if len(m):
            st = filt.predict(prev, t - m.f[:, _T])
            pred = filt.output(st)
            xp, vp = pred.x[:, :3], pred.var[:, :3]
        else:
            st, xp, vp = {}, np.zeros((0, 3)), np.zeros((0, 3))
        kind = m.i[:, _KIND]
        free = np.ones(n_plot, bool)

        # --- confirmed tracks: gate and assign
        conf = np.flatnonzero(kind == _CONF)
        alt_now = _alt_at(m.f, t, cfg.altitude.q_m2ps3)
        o, p, c = tracking_pairs(plots, free, m.i[conf, _RUN], xp[conf], vp[conf], cfg, m.i[conf, _IDENT],
                                 alt_now[conf])
        plot_of_conf = assign(o, p, c, len(conf), n_plot, cfg.assignment)
        free[plot_of_conf[plot_of_conf >= 0]] = False
        opens = free.copy()                      # plots that open new tentative tracks

        # --- initiation
        win, plot_of_win = empty, empty          # three-scan: hypotheses confirmed now
        pair_obj, pair_plot = empty, empty       # three-scan: new hypotheses (stage-1 object, plot)
        tent, plot_of_tent = empty, empty        # M-of-N: tentatives (their plot or −1)
        wait = empty                             # three-scan: objects waiting for a measured plot
        if three:
            # a scan of the test is a measured plot: a target's extrapolated row between its
            # radars' scans is no evidence, so it neither opens, pairs nor confirms
            measured = free & plots.fresh
            gap = cfg.initiation_gap_s                # an object whose wait is over takes no plot
            hyp = np.flatnonzero(kind == _HYP)
            hyp = hyp[t - m.f[hyp, _T2] <= gap]
            o, p, c = _confirm_pairs(plots, measured, m.take(hyp), t, cfg)
            if len(o):
                plot_of_hyp = assign(o, p, c, len(hyp), n_plot, cfg.assignment)
                chosen = plot_of_hyp[o] == p
                cost_of = np.full(len(hyp), np.inf)
                cost_of[o[chosen]] = c[chosen]
                got = np.flatnonzero(plot_of_hyp >= 0)
                got = _resolve_conflicts(got, cost_of[got], m.i[hyp[got], _ROOT], m.i[hyp[got], _UID2])
                win, plot_of_win = hyp[got], plot_of_hyp[got]
                free[plot_of_win] = False
                measured &= free
            opens = measured.copy()
            s1 = np.flatnonzero(kind == _TENT)
            s1 = s1[t - m.f[s1, _T1] <= gap]
            if len(s1):
                o, p = _annulus_pairs(plots, measured, m.take(s1), t, cfg)
                pair_obj, pair_plot = s1[o], p
            # the others wait for their target's next measured plot
            wait = np.concatenate([np.setdiff1d(s1, pair_obj), np.setdiff1d(hyp, win)])
        else:
            tent = np.flatnonzero(kind == _TENT)
            one = m.i[tent, _HITS] == 1
            o1, p1 = _annulus_pairs(plots, free, m.take(tent[one]), t, cfg)
            o1 = np.flatnonzero(one)[o1]
            c1 = likelihood_cost(plots.z[p1] - xp[tent[o1]], vp[tent[o1]] + plots.r[p1])
            many = np.flatnonzero(~one)
            o2, p2, c2 = tracking_pairs(plots, free, m.i[tent[many], _RUN], xp[tent[many]], vp[tent[many]], cfg,
                                        m.i[tent[many], _IDENT], alt_now[tent[many]])
            plot_of_tent = assign(np.r_[o1, many[o2]], np.r_[p1, p2], np.r_[c1, c2], len(tent), n_plot,
                                   cfg.assignment)
            used = plot_of_tent >= 0
            free[plot_of_tent[used]] = False
            opens[plot_of_tent[used & ~one]] = False

        # --- one filter update for everything that continues
        misses = np.where(plot_of_conf >= 0, 0, m.i[conf, _MISS] + 1)
        alive = misses < cfg.max_misses
        idx = np.concatenate([conf[alive], win, pair_obj, wait, tent])
        pidx = np.concatenate([plot_of_conf[alive], plot_of_win, pair_plot, np.full(len(wait), -1), plot_of_tent])
        mask = pidx >= 0
        safe = np.where(mask, pidx, 0)
        z, r = plots.z[safe], plots.r[safe]
        mu = m.take(idx)
        # the filter takes only new measurements, at their own time epoch − age
        fresh = mask & plots.fresh[safe]
        age = np.where(fresh, plots.age[safe], 0.0)
        if len(idx):
            base = _take_state(st, idx, len(m))
            if (age > 0).any():
                base = filt.predict(_take_state(prev, idx, len(m)), np.maximum(t - age - mu.f[:, _T], 0.0))
            rm = plots.rm[safe]
            su, inn = filt.update(base, plots.zm[safe], rm if filt.full_r else np.einsum("bii->bi", rm), fresh)
            if cfg.use_turn_rate:
                su = filt.observe_turn_rate(su, plots.omega[safe], fresh)
            if cfg.use_velocity:
                su = _observe_velocity(filt, su, plots, safe, fresh, cfg, t - age - mu.f[:, _T])
        else:
            su, inn = {}, None
        mu.f[:, _ALT] = _alt_step(mu.f, t, plots.alt[safe], mask, cfg.altitude.q_m2ps3)
        if cfg.use_vertical_rate:
            mu.f[:, _ALT] = _alt_rate_step(mu.f[:, _ALT], plots.vr[safe], fresh, cfg, t - mu.f[:, _TA])
        # a track keeps the last Mode S address its plots carried
        got = mask & (plots.ident[safe] >= 0)
        mu.i[:, _IDENT] = np.where(got, plots.ident[safe], mu.i[:, _IDENT])
        mu.f[:, _T] = t - age
        mu.f[:, _TA] = t
        n_c, n_w, n_p = int(alive.sum()), len(win), len(pair_obj)
        mu.i[:n_c, _MISS] = misses[alive]
        newly = np.zeros(len(idx), bool)
        if three:
            mu.i[n_c:n_c + n_w, _KIND] = _CONF
            newly[n_c:n_c + n_w] = True
            hs = slice(n_c + n_w, n_c + n_w + n_p)
            mu.i[hs, _KIND] = _HYP
            mu.f[hs, _P2] = plots.z[pair_plot]
            mu.f[hs, _RZ2] = plots.r[pair_plot, 2]
            mu.f[hs, _T2] = t
            mu.i[hs, _UID2] = plots.uid[pair_plot]
            keep = np.ones(len(idx), bool)
        else:
            ts = slice(n_c, len(idx))
            hit = mask[ts]
            mu.i[ts, _HITS] += hit
            mu.i[ts, _SCANS] += 1
            mu.f[ts, _P1] = np.where(hit[:, None], z[ts], mu.f[ts, _P1])
            mu.f[ts, _T1] = np.where(hit, t, mu.f[ts, _T1])
            mu.f[ts, _RZ1] = np.where(hit, r[ts, 2], mu.f[ts, _RZ1])
            ok = mu.i[ts, _HITS] >= cfg.m
            newly[ts] = ok
            mu.i[ts, _KIND] = np.where(ok, _CONF, _TENT)
            keep = np.ones(len(idx), bool)
            keep[ts] = ok | (mu.i[ts, _HITS] + (cfg.n - mu.i[ts, _SCANS]) >= cfg.m)

        # --- track ids of the newly confirmed: the next ids of their run, in plot order
        nid = np.flatnonzero(newly)
        if len(nid):
            rr = mu.i[nid, _RUN]
            order = np.argsort(rr, kind="stable")
            srt = rr[order]
            rank = np.empty(len(nid), np.int64)
            rank[order] = np.arange(len(nid)) - np.searchsorted(srt, srt)
            mu.i[nid, _ID] = next_id[rr] + rank
            next_id += np.bincount(rr, minlength=n_runs)

        # --- emit the confirmed and coasting rows
        emit = np.flatnonzero(mu.i[:, _KIND] == _CONF)
        if len(emit):
            se = _take_state(su, emit, len(idx))
            if (age[emit] > 0).any():               # reported at the epoch
                se = filt.predict(se, t - mu.f[emit, _T])
            oe = filt.output(se)
            upd = mask[emit]
            emitted.add(run=mu.i[emit, _RUN], epoch=np.full(len(emit), ix.epochs[k]), track_id=mu.i[emit, _ID],
                        x=oe.x, var=oe.var, cov=full_cov(oe).reshape(-1, 36), nu=inn.nu[emit], nis=inn.nis[emit],
                        upd=upd, alt=mu.f[emit, _ALT],
                        tid=plots.tid[safe[emit]], probs=oe.probs)

        # --- new tentatives from the plots no track or confirmation took
        newp = np.flatnonzero(opens)
        rn = plots.rm[newp]
        sn = filt.init(plots.zm[newp], rn if filt.full_r else np.einsum("bii->bi", rn)) if len(newp) else {}
        if cfg.use_velocity and len(newp):
            sn = _observe_velocity(filt, sn, plots, newp, plots.fresh[newp], cfg, np.zeros(len(newp)))
        mn = _Objects.new(plots.run[newp], t, plots.z[newp], plots.r[newp, 2], plots.uid[newp], plots.alt[newp],
                           plots.ident[newp])
        mn.f[:, _T] = t - plots.age[newp]
        if cfg.use_vertical_rate and len(newp):
            mn.f[:, _ALT] = _alt_rate_step(mn.f[:, _ALT], plots.vr[newp], plots.fresh[newp], cfg, np.zeros(len(newp)))
        kept = np.flatnonzero(keep)
        state = _join_states(_take_state(state, idle, len(objs)) if len(idle) else {},
                             _take_state(su, kept, len(idx)) if len(idx) else {}, sn)
        objs = _Objects.concat(objs.take(idle) if len(idle) else _Objects.empty(), mu.take(kept), mn)

    return emitted, Bank(f=objs.f, i=objs.i, next_id=next_id, filt_state=state)


def _observe_velocity(filt: TrackFilter, state: State, plots: Plots, rows: NDArray, mask: NDArray,
                      cfg: TrackerConfig, dt: NDArray) -> State:
    """``state`` given the downlinked velocities of ``plots`` rows ``rows`` where ``mask``, each
    used only if its NIS against the state's own velocity estimate is within
    ``cfg.velocity_gate`` (a misread or other aircraft's register is left out), the gate's
    covariance grown by the acceleration allowed over the ``dt`` since the previous update."""
    if type(filt).observe_velocity is TrackFilter.observe_velocity:
        return state
    v = plots.vm[rows]
    use = mask & np.isfinite(v).all(axis=1)
    if not use.any():
        return state
    r = velocity_covariance(v, plots.omega[rows], cfg)
    out = filt.output(state)
    allow = (cfg.velocity_accel_mps2 * np.maximum(dt, 0.0)) ** 2
    s = full_cov(out)[:, 3:5, 3:5] + r + allow[:, None, None] * np.eye(2)
    d = np.where(use[:, None], v - out.x[:, 3:5], 0.0)
    det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        nis = (s[:, 1, 1] * d[:, 0] ** 2 - 2.0 * s[:, 0, 1] * d[:, 0] * d[:, 1] + s[:, 0, 0] * d[:, 1] ** 2) / det
    return filt.observe_velocity(state, v, r, use & (nis <= cfg.velocity_gate))


def _resolve_conflicts(got: NDArray, cost: NDArray, root: NDArray, uid2: NDArray) -> NDArray:
    """Among confirming hypotheses, keep the cheapest per scan-1 plot, then per scan-2 plot."""
    if len(got) < 2:
        return got
    order = np.argsort(cost, kind="stable")
    got, root, uid2 = got[order], root[order], uid2[order]
    _, first = np.unique(root, return_index=True)
    sel = np.sort(first)
    got, uid2 = got[sel], uid2[sel]
    _, first = np.unique(uid2, return_index=True)
    return np.sort(got[np.sort(first)])



@dataclass(frozen=True)
class Bank:
    """One filter's tracker over every batch run of a :class:`TrackState`.

    ``f``/``i``: the objects (stage-1 tentatives, scan-2 hypotheses, confirmed tracks) as the
    packed rows of ``_Objects`` — times in float seconds since ``TrackState.origin_us``,
    ``_RUN`` = batch run index, track ids, miss/hit/scan counters, the uids of their scan-1 and
    scan-2 plots; ``filt_state``: the filter bank :data:`State` of the same objects (object axis
    first, same order); ``next_id``: the next track id of every batch run."""

    f: NDArray
    i: NDArray
    next_id: NDArray
    filt_state: State

    @staticmethod
    def empty() -> "Bank":
        return Bank(np.zeros((0, _NF)), np.zeros((0, _NI), np.int64), np.zeros(0, np.int64), {})
