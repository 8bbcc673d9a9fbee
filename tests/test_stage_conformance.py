"""Every streamed stage of :data:`tertiary.pipeline.plan.STAGES` follows the stage contract
(:mod:`tertiary.core.stage`), checked on one small simulated run:

(a) stepping window by window gives what one step over the whole run gives (rows concatenated,
    totals added up, keyed sums added up by key, the final state equal);
(b) an empty window leaves the state as it was (but for the time it has reached);
(c) ``step`` does not modify the state it is given;
(d) the state pickles, and the unpickled state gives the same next step;
(e) a reversed window, and rows outside the window, are refused with the window error.

The stages' inputs are the whole-run outputs of the stages before them (each stage stepped once
over :meth:`Window.unbounded`), cut into the windows by their time column.
"""

from __future__ import annotations

import dataclasses
import pickle
from dataclasses import dataclass

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.core.errors import DataError, OptionError
from tertiary.core.units import US
from tertiary.evaluation.evaluate import Reference
from tertiary.pipeline import PipelineConfig, plan, screen
from tertiary.core.stage import T_MAX_US, T_MIN_US, Stage, Window
from tertiary.runtime.windows import concat_parts
from tertiary.simulate import load_scenario, simulate
from tertiary.stages import align
from tertiary.stages.clustering import ClusteringConfig
from tertiary.stages.flight_data import check_flight_plans, correlate, departure_plans
from tertiary.stages.fusion import measured_plots

#: state fields that hold the end of the last window stepped (an empty window moves them on)
CLOCK_FIELDS = {"t_us", "reached_us"}
#: how each input is cut into windows: "in" — rows with the column in [t0, t1); "upto" — rows
#: with the column before t1, "all" — every row (what a stage may look back at: extra rows are
#: ignored)
IN, UPTO, ALL = "in", "upto", "all"
#: the stages the pipeline steps, then those with the same contract that it does not
EVERY_STAGE = (*plan.STAGES, *plan.EXTRA_STAGES)


@dataclass
class Case:
    """A stage built for the run and its whole-run inputs, with how each input is windowed."""

    stage: Stage
    inputs: dict[str, pl.DataFrame]
    cut: dict[str, tuple[str, str]]        # input -> (time column, IN or UPTO)


def _step_whole(stage: Stage, inputs: dict[str, pl.DataFrame]) -> dict[str, pl.DataFrame]:
    return stage.step(stage.init(), inputs, Window.unbounded())[0]


def _build_cases() -> tuple[dict[str, Case], list[int]]:
    """Terminal-area, 20 aircraft, 240 s: every stage of :data:`plan.STAGES` and its inputs."""
    sc = load_scenario("terminal-area")
    sc = dataclasses.replace(sc, duration_s=240.0, traffic=dataclasses.replace(sc.traffic, aircraft=20))
    ds = simulate(sc)
    # a display capacity some pictures exceed: clusters, and pictures left unclustered between them
    cfg = PipelineConfig(evaluation=False, methods=("arithmetic", "information"), filters=("singer",),
                         stca_lookaheads_s=(), clustering=ClusteringConfig(display_capacity=12))
    ing = screen(ds, cfg)
    plans, _ = check_flight_plans(ds.flight_plans)
    reports = correlate(ing.reports, plans)
    times = reports["time"].dt.epoch("us")
    ctx = dataclasses.make_dataclass("Ctx", ["radars", "origin", "grid_origin_us", "filters", "departure_plans",
                                             "reference"])(
        ing.radars, ds.origin, align.grid_origin_us(int(times.min())), ("singer",),
        departure_plans(plans, ds.origin), Reference(ing.truth))
    stages = plan.build_stages(cfg, ctx, EVERY_STAGE)
    cases: dict[str, Case] = {}

    def add(name: str, inputs: dict[str, pl.DataFrame], cut: dict[str, tuple[str, str]]) -> dict[str, pl.DataFrame]:
        cases[name] = Case(stages[name], inputs, cut)
        return _step_whole(stages[name], inputs)

    aligned = add("align", {"reports": reports}, {"reports": ("time", IN)})["aligned"]
    codes = reports.select("run", "report_id", "mode_3a", "time")
    aligned = add("departures", {"aligned": aligned, "reports": reports, "codes": codes},
                  {"aligned": ("epoch", IN), "reports": ("time", IN), "codes": ("time", UPTO)})["aligned"]
    assoc = add("associate", {"aligned": aligned}, {"aligned": ("epoch", IN)})["associations"]
    rows = aligned.with_columns(assoc["target_id"]).sort("run", "epoch", "target_id", "radar_id")
    plots = measured_plots(reports, ing.radars, ds.origin, cfg.align.local_tracker.altitude_sigma_m)
    fused = add("fuse", {"rows": rows, "plots": plots}, {"rows": ("epoch", IN), "plots": ("", ALL)})["fused"]
    keys = rows.select("run", "epoch", "target_id").unique(maintain_order=True)
    central = add("centralized", {"reports": reports, "associations": assoc, "keys": keys},
                  {"reports": ("time", UPTO), "associations": ("epoch", IN), "keys": ("epoch", IN)})["centralized"]
    add("cluster", {"fused": pl.concat([fused, central], how="diagonal_relaxed")}, {"fused": ("epoch", IN)})
    tracks = add("track", {"fused": fused}, {"fused": ("epoch", IN)})["tracks"]
    picture = tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("method"))
    conflicts = add("conflicts", {"picture": picture}, {"picture": ("epoch", IN)})["conflicts"]
    # the curves' stage with points of both threshold families (the run above draws none)
    stages["stca_curves"] = plan.build_stage("stca_curves", dataclasses.replace(
        cfg, stca_lookaheads_s=(90.0,), stca_confidences=(0.9,), stca_fixed_m=(300.0,)), ctx)
    curves = add("stca_curves", {"picture": picture}, {"picture": ("epoch", IN)})["curve_rows"]
    assert curves["setting"].n_unique() == 2 and curves["alert"].any(), "the curve case screens nothing"
    # the evaluation's matching, with the multi-target state and the seed metrics (the run above
    # scores no picture)
    stages["evaluation"] = plan.build_stage("evaluation", dataclasses.replace(cfg, evaluation=True), ctx)
    matched = add("evaluation", {"fused": pl.concat([fused, central], how="diagonal_relaxed"), "tracks": tracks,
                                 "aligned": aligned},
                  {"fused": ("epoch", IN), "tracks": ("epoch", IN), "aligned": ("epoch", IN)})
    rows = pl.concat([f for k, f in matched.items() if k.startswith("matched.") and f.height], how="diagonal_relaxed")
    assert rows.filter(pl.col("method") == "information+singer")["truth_id"].is_not_null().any(), "nothing matched"
    assert matched["scored"].filter(pl.col("method") == "information+singer").height, "nothing scored"
    epochs = picture.select("epoch").unique()
    add("alert_confirmation", {"conflicts": conflicts, "epochs": epochs},
        {"conflicts": ("epoch", IN), "epochs": ("epoch", IN)})
    lo, hi = int(times.min()), int(times.max())
    cuts = [lo + int(f * (hi - lo)) + 123 for f in (0.3, 0.55, 0.8)]
    return cases, cuts


@pytest.fixture(scope="module")
def run() -> tuple[dict[str, Case], list[int]]:
    return _build_cases()


def _window_inputs(case: Case, w: Window) -> dict[str, pl.DataFrame]:
    out = {}
    for name, frame in case.inputs.items():
        col, how = case.cut[name]
        if how == ALL:
            out[name] = frame
            continue
        t = pl.col(col).dt.epoch("us")
        cond = t < w.t1_us if how == UPTO else (t >= w.t0_us) & (t < w.t1_us)
        out[name] = frame.filter(cond)
    return out


def _windows(cuts: list[int]) -> list[Window]:
    edges = [T_MIN_US, *cuts, T_MAX_US]
    return [Window(i, a, b) for i, (a, b) in enumerate(zip(edges[:-1], edges[1:]))]


def _stepped(case: Case, windows: list[Window], state=None, roundtrip: bool = False
             ) -> tuple[list[dict[str, pl.DataFrame]], object]:
    state = case.stage.init() if state is None else state
    outs = []
    for w in windows:
        out, state = case.stage.step(state, _window_inputs(case, w), w)
        outs.append(out)
        if roundtrip:
            state = pickle.loads(pickle.dumps(state))
    return outs, state


# --------------------------------------------------------------------------- comparison


def _canonical(frame: pl.DataFrame) -> pl.DataFrame:
    """Rows in a canonical order: sorted by the exact columns, then by the float ones."""
    flat = [c for c, d in frame.schema.items() if not d.is_nested() and d != pl.Object]
    exact = [c for c in flat if not frame.schema[c].is_float()]
    by = exact + [c for c in flat if c not in exact]
    return frame.sort(by, nulls_last=True, maintain_order=True) if by and frame.height else frame


def assert_same_frame(a: pl.DataFrame, b: pl.DataFrame, what: str = "") -> None:
    """Equal tables up to row order (a step's row order is not part of the contract; floats to 1e-9)."""
    assert sorted(a.columns) == sorted(b.columns), f"{what}: columns {a.columns} != {b.columns}"
    assert a.height == b.height, f"{what}: {a.height} rows != {b.height}"
    if a.height:
        assert_frame_equal(_canonical(a), _canonical(b.select(a.columns)), rel_tol=1e-9, abs_tol=1e-9)


def assert_same_state(a: object, b: object, ignore: frozenset[str] = frozenset(), path: str = "state") -> None:
    """Equal states: frames, arrays, dataclasses, mappings, sequences and plain objects walked;
    fields named in ``ignore`` skipped."""
    def same(x: object, y: object, where: str) -> None:
        assert_same_state(x, y, ignore, where)

    if isinstance(a, pl.DataFrame) or isinstance(b, pl.DataFrame):
        assert isinstance(a, pl.DataFrame) and isinstance(b, pl.DataFrame), path
        assert_same_frame(a, b, path)
    elif isinstance(a, pl.Series):
        same(a.to_frame(), b.to_frame(), path)
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.shape == b.shape, path
        if a.dtype == object:
            for i, (x, y) in enumerate(zip(a.ravel(), b.ravel())):
                same(x, y, f"{path}[{i}]")
        elif a.dtype.kind in "fc":
            assert np.allclose(a, b, rtol=1e-9, atol=1e-9, equal_nan=True), path
        else:
            assert np.array_equal(a, b), path
    elif dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b), path
        for f in dataclasses.fields(a):
            if f.name not in ignore:
                same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{path}: keys {set(a) ^ set(b)}"
        for k in a:
            same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            same(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert (np.isnan(a) and np.isnan(b)) or np.isclose(a, b, rtol=1e-9, atol=1e-9), path
    elif hasattr(a, "__dict__") and not isinstance(a, type):
        assert type(a) is type(b), path
        same(vars(a), vars(b), path)
    elif hasattr(type(a), "__slots__"):
        assert type(a) is type(b), path
        for slot in type(a).__slots__:
            same(getattr(a, slot, None), getattr(b, slot, None), f"{path}.{slot}")
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def _joined(stage: Stage, outs: list[dict[str, pl.DataFrame]]) -> dict[str, pl.DataFrame]:
    """Window outputs as one run's: rows concatenated, totals added up, keyed sums added up by
    key, the last snapshot."""
    got = {}
    for name in {n: None for o in outs for n in o}:
        frames = [o[name] for o in outs if name in o]
        if name in stage.totals:
            got[name] = pl.concat(frames).sum()
        elif name in stage.sums:
            both, add = pl.concat(frames), stage.sums[name]
            got[name] = both.group_by([c for c in both.columns if c not in add]).agg(pl.col(add).sum())
        elif name in stage.snapshots:
            got[name] = frames[-1]
        else:
            got[name] = concat_parts(frames)
    return got


# --------------------------------------------------------------------------- the checks


def test_every_stage_is_covered_and_built_in_order(run):
    cases, _ = run
    assert set(cases) == set(EVERY_STAGE), "a stage of plan.STAGES has no conformance case"
    assert [c.stage.name for c in cases.values()] == list(EVERY_STAGE)
    for case in cases.values():
        assert isinstance(case.stage, Stage)


@pytest.mark.parametrize("name", EVERY_STAGE)
def test_windowed_steps_equal_one_whole_step(run, name):
    cases, cuts = run
    case = cases[name]
    whole, whole_state = case.stage.step(case.stage.init(), case.inputs, Window.unbounded())
    outs, state = _stepped(case, _windows(cuts))
    got = _joined(case.stage, outs)
    assert set(got) == set(whole)
    assert sum(f.height for f in whole.values()) > 0, f"{name}: the case exercises no row"
    for table, frame in whole.items():
        assert_same_frame(got[table], frame, what=f"{name}.{table}")
    assert_same_state(state, whole_state)


def _first_window(cuts: list[int]) -> Window:
    return _windows(cuts)[0]


@pytest.mark.parametrize("name", EVERY_STAGE)
def test_an_empty_window_leaves_the_state_unchanged(run, name):
    cases, cuts = run
    case = cases[name]
    w0 = _first_window(cuts)
    _, state = _stepped(case, [w0])
    empty = Window(1, w0.t1_us, w0.t1_us + 1)          # 1 µs: no report, no epoch
    inputs = {k: v.clear() for k, v in _window_inputs(case, empty).items()}
    out, after = case.stage.step(state, inputs, empty)
    for table, frame in out.items():
        if table in case.stage.totals:
            assert frame.select(pl.all().sum()).row(0) == (0,) * frame.width, table
        elif table not in case.stage.snapshots:
            assert frame.height == 0, table
    assert_same_state(after, state, ignore=frozenset(CLOCK_FIELDS))


@pytest.mark.parametrize("name", EVERY_STAGE)
def test_step_does_not_modify_its_input_state(run, name):
    cases, cuts = run
    case = cases[name]
    ws = _windows(cuts)
    _, state = _stepped(case, ws[:1])
    before = pickle.loads(pickle.dumps(state))
    case.stage.step(state, _window_inputs(case, ws[1]), ws[1])
    assert_same_state(state, before)


@pytest.mark.parametrize("name", EVERY_STAGE)
def test_the_state_pickles_and_steps_on_the_same(run, name):
    cases, cuts = run
    case = cases[name]
    ws = _windows(cuts)
    _, state = _stepped(case, ws[:1])
    copy = pickle.loads(pickle.dumps(state))
    out_a, a = case.stage.step(state, _window_inputs(case, ws[1]), ws[1])
    out_b, b = case.stage.step(copy, _window_inputs(case, ws[1]), ws[1])
    assert set(out_a) == set(out_b)
    for table in out_a:
        assert_same_frame(out_b[table], out_a[table], what=f"{name}.{table}")
    assert_same_state(b, a)


@pytest.mark.parametrize("name", EVERY_STAGE)
def test_a_bad_window_is_refused(run, name):
    cases, cuts = run
    case = cases[name]
    mid = _windows(cuts)[1]
    reversed_ = Window(1, mid.t1_us, mid.t0_us)
    with pytest.raises(OptionError, match="ends before it starts"):
        case.stage.step(case.stage.init(), _window_inputs(case, mid), reversed_)
    with pytest.raises(DataError, match="outside the window"):
        case.stage.step(case.stage.init(), case.inputs, mid)


def test_the_window_value():
    w = Window.unbounded()
    assert (w.t0_us, w.t1_us) == (T_MIN_US, T_MAX_US) and w.open_start and w.open_end and not w.bounded
    assert Window(3, 0, 60 * US).bounded and not Window(3, 0, 60 * US).last
    with pytest.raises(dataclasses.FrozenInstanceError):
        w.t0_us = 0          # type: ignore[misc]
