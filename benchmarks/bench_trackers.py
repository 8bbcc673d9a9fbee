"""Tracker throughput: 10 000 simultaneous tracks, one predict + update per track per step.

Measures, in one run on the same inputs: track updates per second of the batched ``singer``
and ``imm`` filters, and of the same job done with filterpy objects in a Python loop (Singer:
three per-axis ``KalmanFilter`` (dim 3, scalar measurement) per track, exactly the decoupled
model of ``singer``; IMM: ``IMMEstimator`` over three horizontal ``KalmanFilter`` (CT 0.001,
CT 0.045, CV) plus a vertical CV ``KalmanFilter`` per track). filterpy is timed on a subset of
tracks and steps (it is linear in both) and scaled to updates/s.
Targets (issue 4): ≥ 1 000 000 Singer updates/s and ≥ 100× the filterpy loop.

    python benchmarks/bench_trackers.py [--tracks 10000] [--steps 50] [--ref-tracks 200]

Accuracy mode (issue 12): the fused picture's and every tracker's position RMSE per fusion
method, from the ``metrics`` the pipeline computes (stage fusion / tracker, ``rmse_pos_m``,
segment ``all``), with the trackers' NEES, and the confirmed / tentative target counts against
the aircraft; recorded in ``results/trackers_accuracy_<label>.json``:

    python benchmarks/bench_trackers.py --accuracy DATASET_DIR --label big-box-n100 \
        [--filters singer,imm_sym,cv_full,singer_full]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from filterpy.kalman import IMMEstimator, KalmanFilter

from _util import record
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


def time_batched(name: str, z, r, steps: int) -> float:
    filt = make_filter(name)
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
    from tertiary.simulate import read_dataset

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--accuracy", metavar="DATASET_DIR", help="run the accuracy mode on this dataset")
    ap.add_argument("--label", default="run", help="accuracy mode: results/trackers_accuracy_<label>.json")
    ap.add_argument("--filters", default="singer,imm_sym,cv_full,singer_full")
    ap.add_argument("--tracks", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--ref-tracks", type=int, default=200)
    ap.add_argument("--ref-steps", type=int, default=10)
    args = ap.parse_args()
    if args.accuracy:
        out = accuracy(args.accuracy, tuple(f for f in args.filters.split(",") if f))
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
    result["targets"] = {"singer_updates_per_s": 1_000_000, "speedup": 100}
    path = record("bench_trackers", result)
    print(json.dumps(result, indent=2))
    print(f"recorded in {path}")


if __name__ == "__main__":
    main()
