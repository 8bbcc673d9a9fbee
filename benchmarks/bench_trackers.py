"""Tracker throughput: 10 000 simultaneous tracks, one predict + update per track per step.

Measures, in one run on the same inputs: track updates per second of the batched ``singer``
and ``imm`` filters, and of the same job done with filterpy objects in a Python loop (Singer:
three per-axis ``KalmanFilter`` (dim 3, scalar measurement) per track, exactly the decoupled
model of ``singer``; IMM: ``IMMEstimator`` over three horizontal ``KalmanFilter`` (CT 0.001,
CT 0.045, CV) plus a vertical CV ``KalmanFilter`` per track). filterpy is timed on a subset of
tracks and steps (it is linear in both) and scaled to updates/s.
Targets: ≥ 1 000 000 Singer updates/s and ≥ 100× the filterpy loop.

    python benchmarks/bench_trackers.py [--tracks 10000] [--steps 50] [--ref-tracks 200]

Accuracy mode: the fused picture's and every tracker's position RMSE per fusion
method, from the ``metrics`` the pipeline computes (stage fusion / tracker, ``rmse_pos_m``,
segment ``all``), with the trackers' NEES, and the confirmed / tentative target counts against
the aircraft; recorded in ``results/trackers_accuracy_<label>.json``:

    python benchmarks/bench_trackers.py --accuracy DATASET_DIR --label big-box-n100 \
        [--filters singer,imm_sym,cv_full,singer_full]

Tracker-stage mode: the secondary tracker stage on one dataset's fusion pictures,
before (the per-(method, filter) loop with the numpy filters: :func:`track` per method) and
after (:func:`track_methods`: (method, run) folded into the batch axis, compiled IMM), for the
full configuration (every method × ``--filters``) and the production one (``information`` ×
``imm_sym``); checks that both give the same rows; and the first-run cost of the compiled
kernels (fresh numba cache vs cached vs numpy, CPU seconds of a fresh process). Recorded in
``results/bench_trackers.json`` (key ``tracker_stage``):

    python benchmarks/bench_trackers.py --stage DATASET_DIR [--filters singer,imm_sym]

Turning mode: on one dataset (e.g. circling or en-route ADS-B trajectories made into truth by
``tertiary simulate adsb --truth FILE``), the ``information`` picture and every tracker of
``--filters``: horizontal RMSE per evaluation segment (``all``, ``phase:*``, ``range:*``,
``alt:*``) from the pipeline's ``metrics`` (stage evaluation), each tracker's NEES, and the
throughput of the turn-capable filters (10 000 tracks, numpy/compiled as shipped). Recorded in
``results/trackers_turning_<label>.json``:

    python benchmarks/bench_trackers.py --turns DATASET_DIR --label circle-wide [--filters imm_sym,imm_ct]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from filterpy.kalman import IMMEstimator, KalmanFilter

from _util import RESULTS, record
from tertiary.filters import make_filter
from tertiary.filters.imm import PAPER_MU0, PAPER_OMEGAS, PAPER_TPM, model_matrices
from tertiary.filters.singer import singer_phi, singer_q

TAU = 4.0
R = 50.0 ** 2


def inputs(n: int, steps: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    p0 = rng.uniform(-1e5, 1e5, (n, 3)) * [1, 1, 0.05]
    v = rng.normal(0, 150, (n, 3)) * [1, 1, 0.02]
    t = np.arange(steps + 1)[:, None, None] * TAU
    z = p0[None] + v[None] * t + rng.normal(0, 50, (steps + 1, n, 3))
    return z, np.full((n, 3), R)


def time_batched(name: str, z, r, steps: int, **params) -> float:
    filt = make_filter(name, **params)
    filt.update(filt.predict(filt.init(z[0, :2], r[:2]), np.full(2, TAU)), z[1, :2], r[:2], np.ones(2, bool))
    n = z.shape[1]
    state = filt.init(z[0], r)
    dt = np.full(n, TAU)
    mask = np.ones(n, bool)
    t = time.perf_counter()
    for k in range(1, steps + 1):
        state = filt.predict(state, dt)
        state, _ = filt.update(state, z[k], r, mask)
    return n * steps / (time.perf_counter() - t)


def time_filterpy_singer(z, steps: int) -> float:
    n = z.shape[1]
    phi, q = singer_phi(TAU, 1 / 30), singer_q(TAU, 1 / 30, 2.0)
    filters = []
    for i in range(n):
        for ax in range(3):
            kf = KalmanFilter(dim_x=3, dim_z=1)
            kf.x = np.array([z[0, i, ax], 0.0, 0.0])
            kf.P = np.diag([R, 300.0 ** 2, 4.0])
            kf.F, kf.Q, kf.H, kf.R = phi, q, np.array([[1.0, 0.0, 0.0]]), np.array([[R]])
            filters.append(kf)
    t = time.perf_counter()
    for k in range(1, steps + 1):
        for i in range(n):
            for ax in range(3):
                kf = filters[3 * i + ax]
                kf.predict()
                kf.update(z[k, i, ax])
    return n * steps / (time.perf_counter() - t)


def time_filterpy_imm(z, steps: int) -> float:
    n = z.shape[1]
    mats = [model_matrices(w, TAU, 1.0) for w in PAPER_OMEGAS]
    h = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    tracks = []
    for i in range(n):
        kfs = []
        for a, q in mats:
            kf = KalmanFilter(dim_x=4, dim_z=2)
            kf.x = np.array([z[0, i, 0], 0.0, z[0, i, 1], 0.0])
            kf.P = np.diag([R, 150.0 ** 2, R, 150.0 ** 2])
            kf.F, kf.Q, kf.H, kf.R = np.asarray(a), np.asarray(q), h, np.eye(2) * R
            kfs.append(kf)
        imm = IMMEstimator(kfs, np.array(PAPER_MU0), np.array(PAPER_TPM))
        vz = KalmanFilter(dim_x=2, dim_z=1)
        vz.x = np.array([z[0, i, 2], 0.0])
        vz.P = np.diag([R, 15.0 ** 2])
        vz.F = np.array([[1.0, TAU], [0.0, 1.0]])
        vz.Q = np.array([[TAU ** 3 / 3, TAU ** 2 / 2], [TAU ** 2 / 2, TAU]])
        vz.H, vz.R = np.array([[1.0, 0.0]]), np.array([[R]])
        tracks.append((imm, vz))
    t = time.perf_counter()
    for k in range(1, steps + 1):
        for i, (imm, vz) in enumerate(tracks):
            imm.predict()
            imm.update(z[k, i, :2])
            vz.predict()
            vz.update(z[k, i, 2])
    return n * steps / (time.perf_counter() - t)


def accuracy(dataset: str, filters: tuple[str, ...]) -> dict:
    """Fused vs tracker RMSE per fusion method (and NEES, target counts) on one dataset."""
    import polars as pl

    from tertiary import pipeline
    from tertiary.io.dataset import read_dataset

    ds = read_dataset(dataset)
    cfg = pipeline.PipelineConfig(filters=filters, safety=False, centralized=False)
    t = time.perf_counter()
    res = pipeline.process(ds, cfg)
    wall = time.perf_counter() - t
    m = res.metrics.filter(pl.col("segment") == "all")

    def value(stage: str, method: str, metric: str) -> float | None:
        v = m.filter((pl.col("stage") == stage) & (pl.col("method") == method) & (pl.col("metric") == metric))
        return float(v["value"][0]) if v.height else None

    table, split = {}, {}
    for meth in cfg.methods:
        row = {"fused": value("fusion", meth, "rmse_pos_m")}
        sp = {"fused": [value("fusion", meth, f"rmse_{k}_m") for k in ("horizontal", "height")]}
        for f in filters:
            row[f] = value("tracker", f"{meth}+{f}", "rmse_pos_m")
            row[f"{f}_nees"] = value("tracker", f"{meth}+{f}", "nees_mean")
            sp[f] = [value("tracker", f"{meth}+{f}", f"rmse_{k}_m") for k in ("horizontal", "height")]
        got = [row[f] for f in filters if row[f] is not None]
        row["best_tracker_below_fused"] = bool(got and row["fused"] is not None and min(got) < row["fused"])
        table[meth], split[meth] = row, sp
    c = res.counts
    return {"dataset": dataset, "runs": int(res.ingested.reports["run"].n_unique()), "reports": c["reports_in"],
            "filters": list(filters), "wall_s": wall, "rmse_pos_m": table,
            "rmse_horizontal_height_m": split,
            "targets": {"aircraft": c["aircraft"], "confirmed": c.get("confirmed_targets"),
                        "tentative": c.get("tentative_targets")}}


def turning(dataset: str, filters: tuple[str, ...], tracks: int = 10_000, steps: int = 20) -> dict:
    """Fused ``information`` vs trackers, horizontal RMSE per evaluation segment, NEES, and the
    batched throughput of each filter."""
    import polars as pl

    from tertiary import pipeline
    from tertiary.io.dataset import read_dataset

    ds = read_dataset(dataset)
    cfg = pipeline.PipelineConfig(methods=("information",), filters=filters, safety=False, centralized=False)
    t = time.perf_counter()
    res = pipeline.process(ds, cfg)
    wall = time.perf_counter() - t
    m = res.metrics
    ev = m.filter((pl.col("stage") == "evaluation") & (pl.col("metric") == "rmse_horizontal_m"))
    pictures = ["information", *(f"information+{f}" for f in filters)]
    per_segment = {}
    for seg in sorted(ev["segment"].unique().to_list()):
        row = {}
        for pic in pictures:
            v = ev.filter((pl.col("segment") == seg) & (pl.col("method") == pic))["value"]
            row[pic] = float(v[0]) if len(v) else None
        per_segment[seg] = row
    nees = {}
    for f in filters:
        v = m.filter((pl.col("stage") == "tracker") & (pl.col("method") == f"information+{f}")
                     & (pl.col("segment") == "all") & pl.col("metric").is_in(["nees_mean", "nees6_mean"]))
        nees[f] = {r["metric"]: r["value"] for r in v.iter_rows(named=True)}
    z, r = inputs(tracks, steps)
    throughput = {f: max(time_batched(f, z, r, steps) for _ in range(2)) for f in filters}
    below = {f: {seg: (row[f"information+{f}"] is not None and row["information"] is not None
                       and row[f"information+{f}"] < row["information"]) for seg, row in per_segment.items()}
             for f in filters}
    return {"dataset": dataset, "filters": list(filters), "wall_s": wall,
            "rmse_horizontal_m": per_segment, "tracker_below_fused": below, "nees": nees,
            "updates_per_s": throughput, "throughput_tracks": tracks}


def _same_rows(a, b) -> bool:
    """Equal tables up to round-off (≤ 1e-9 of each float column's scale)."""
    import polars as pl

    if a.columns != b.columns or a.height != b.height:
        return False
    for c in a.columns:
        x, y = a[c], b[c]
        inner = y.dtype.inner if isinstance(y.dtype, (pl.List, pl.Array)) else y.dtype
        if not inner.is_float():
            if not x.equals(y):
                return False
            continue
        if isinstance(y.dtype, pl.List):
            x, y = x.explode(), y.explode()
        elif isinstance(y.dtype, pl.Array):
            x, y = x.arr.explode(), y.arr.explode()
        u, v = x.cast(pl.Float64).to_numpy(), y.cast(pl.Float64).to_numpy()
        ok = ~np.isnan(v)
        if not np.array_equal(np.isnan(u), np.isnan(v)):
            return False
        if ok.any() and (np.abs(u[ok] - v[ok]) > 1e-9 * (np.abs(v[ok]) + np.sqrt(np.mean(v[ok] ** 2)))).any():
            return False
    return True


_FIRST_RUN = """
import resource, sys, time, numpy as np
from tertiary.filters import make_filter
f = make_filter("imm_sym", compiled=sys.argv[1] == "1")
s = f.init(np.full((5, 3), 1e4), np.full((5, 3), 1e4))
t = time.perf_counter()
s, _ = f.update(f.predict(s, np.ones(5)), np.full((5, 3), 1e4), np.full((5, 3), 1e4), np.ones(5, bool))
u = resource.getrusage(resource.RUSAGE_SELF)
print(time.perf_counter() - t, u.ru_utime + u.ru_stime)
"""


def first_run_cost() -> dict:
    """CPU seconds of a fresh process doing one imm_sym predict + update: compiled with an empty
    numba cache (a fresh install), compiled with the cache filled by that run, numpy only."""
    import os
    import subprocess
    import sys
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        for label, flag in (("fresh_cache", "1"), ("cached", "1"), ("numpy", "0")):
            res = subprocess.run([sys.executable, "-c", _FIRST_RUN, flag], env=env, check=True,
                                 capture_output=True, text=True)
            first_call, cpu = map(float, res.stdout.split())
            out[label] = {"first_call_s": first_call, "process_cpu_s": cpu}
    out["compile_extra_cpu_s"] = out["fresh_cache"]["process_cpu_s"] - out["numpy"]["process_cpu_s"]
    out["cached_extra_cpu_s"] = out["cached"]["process_cpu_s"] - out["numpy"]["process_cpu_s"]
    return out


def tracker_stage(dataset: str, filters: tuple[str, ...], reps: int = 2) -> dict:
    """Tracker stage seconds before (per-(method, filter) loop, numpy filters) and after
    (folded batch, compiled IMM) on a dataset's fusion pictures; full and production sets."""
    import inspect

    import polars as pl

    from tertiary import pipeline
    from tertiary.filters.base import REGISTRY
    from tertiary.io.dataset import read_dataset
    from tertiary.stages.tracking.tracker import track, track_methods

    ds = read_dataset(dataset)
    res = pipeline.process(ds, pipeline.PipelineConfig(filters=(), safety=False, centralized=False))
    pictures = res.fused.filter(pl.col("method") != "centralized")

    def numpy_filter(name: str):
        ok = "compiled" in inspect.signature(REGISTRY[name]).parameters
        return make_filter(name, compiled=False) if ok else make_filter(name)

    def before(pics: pl.DataFrame, names: tuple[str, ...]) -> pl.DataFrame:
        parts = [track(pics.filter(pl.col("method") == m), numpy_filter(n), pipeline.PipelineConfig().tracker)
                 for m in sorted(pics["method"].unique().to_list()) for n in names]
        return pl.concat(parts, how="vertical")

    def after(pics: pl.DataFrame, names: tuple[str, ...]) -> pl.DataFrame:
        return track_methods(pics, list(names))

    def best(fn, *args) -> tuple[float, pl.DataFrame]:
        times, out = [], None
        for _ in range(reps):
            t = time.perf_counter()
            out = fn(*args)
            times.append(time.perf_counter() - t)
        return min(times), out

    after(pictures.head(2000), ("imm_sym",))                    # compile / load the kernels first
    result = {"dataset": dataset, "reports": int(ds.reports.height), "pictures_rows": pictures.height,
              "methods": sorted(pictures["method"].unique().to_list()), "epochs": int(pictures["epoch"].n_unique())}
    configs = {"full": (pictures, filters),
               "production": (pictures.filter(pl.col("method") == "information"), ("imm_sym",))}
    for label, (pics, names) in configs.items():
        tb, ob = best(before, pics, names)
        ta, oa = best(after, pics, names)
        result[label] = {"filters": list(names), "methods": int(pics["method"].n_unique()),
                         "before_s": tb, "after_s": ta, "speedup": tb / ta, "rows": oa.height,
                         "same_rows": _same_rows(oa, ob)}
    result["first_run"] = first_run_cost()
    return result


def _merge(key: str, payload: dict):
    """Update one section of results/bench_trackers.json, keeping the others."""
    path = RESULTS / "bench_trackers.json"
    old = json.loads(path.read_text()) if path.exists() else {}
    old.pop("machine", None)
    old[key] = payload
    return record("bench_trackers", old)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--accuracy", metavar="DATASET_DIR", help="run the accuracy mode on this dataset")
    ap.add_argument("--label", default="run", help="accuracy mode: results/trackers_accuracy_<label>.json")
    ap.add_argument("--stage", metavar="DATASET_DIR", help="run the tracker-stage mode on this dataset")
    ap.add_argument("--turns", metavar="DATASET_DIR", help="run the turning mode on this dataset")
    ap.add_argument("--filters", default=None, help="accuracy: singer,imm_sym,cv_full,singer_full; "
                                                    "stage: singer,imm_sym")
    ap.add_argument("--tracks", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--ref-tracks", type=int, default=200)
    ap.add_argument("--ref-steps", type=int, default=10)
    args = ap.parse_args()
    if args.stage:
        out = tracker_stage(args.stage, tuple(f for f in (args.filters or "singer,imm_sym").split(",") if f))
        path = _merge("tracker_stage", out)
        print(json.dumps(out, indent=2))
        print(f"recorded in {path}")
        return
    if args.turns:
        out = turning(args.turns, tuple(f for f in (args.filters or "imm_sym,imm_ct").split(",") if f))
        path = record(f"trackers_turning_{args.label}", out)
        print(json.dumps(out, indent=2))
        print(f"recorded in {path}")
        return
    if args.accuracy:
        filters = args.filters or "singer,imm_sym,cv_full,singer_full"
        out = accuracy(args.accuracy, tuple(f for f in filters.split(",") if f))
        path = record(f"trackers_accuracy_{args.label}", out)
        print(json.dumps(out, indent=2))
        print(f"recorded in {path}")
        return
    z, r = inputs(args.tracks, args.steps)
    zr = z[: args.ref_steps + 1, : args.ref_tracks]
    result = {"tracks": args.tracks, "steps": args.steps, "scan_s": TAU,
              "reference_subset": {"tracks": args.ref_tracks, "steps": args.ref_steps}}
    for name, ref in (("singer", time_filterpy_singer), ("imm", time_filterpy_imm)):
        ours = max(time_batched(name, z, r, args.steps) for _ in range(3))
        theirs = ref(zr, args.ref_steps)
        result[name] = {"updates_per_s": ours, "filterpy_loop_updates_per_s": theirs, "speedup": ours / theirs}
        if name == "imm":       # the numpy path beside the compiled kernels
            result[name]["numpy_updates_per_s"] = max(time_batched(name, z, r, args.steps, compiled=False)
                                                      for _ in range(3))
    result["targets"] = {"singer_updates_per_s": 1_000_000, "speedup": 100}
    path = RESULTS / "bench_trackers.json"
    if path.exists() and "tracker_stage" in (old := json.loads(path.read_text())):
        result["tracker_stage"] = old["tracker_stage"]
    path = record("bench_trackers", result)
    print(json.dumps(result, indent=2))
    print(f"recorded in {path}")


if __name__ == "__main__":
    main()
