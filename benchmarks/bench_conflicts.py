"""Conflict-prediction throughput: 1 000 and 10 000 simultaneous aircraft.

Heights are geodetic (``frame=`` the system origin, the conversion is part of the timing).
Random terminal-like traffic (speeds 70–250 m/s, random headings, heights 300–12 000 m, 30 %
climbing or descending at 5–15 m/s, full 6×6 covariances with 50–150 m position and 2–8 m/s
velocity sigmas) in a 200 km × 200 km box, several epochs (aircraft flown on 5 s between
epochs). Measured in a fresh process per configuration (``run_isolated``): seconds per epoch of
``safety.predict_conflicts`` (one call per epoch, best and median over the epochs × repeats;
and, in another process, one call for all epochs at once), candidate pairs examined by the
KD-tree screen, output rows and alerts, and peak resident memory; ``*_call_rss_mib`` is the
peak minus the process's RSS after imports and data generation (the prediction's own
footprint).

The fixed 200 km box makes the density — and so the number of candidate pairs — grow with N
(pairs ∝ N²); ``--density`` adds runs whose box grows with √N (constant density, pairs ∝ N),
where memory is linear in N. Target (issue): 10 000 aircraft < 0.5 s per epoch.

    python benchmarks/bench_conflicts.py [--aircraft 1000 10000] [--epochs 5] [--repeat 3]
                                         [--modes corrected seed] [--density]
"""

from __future__ import annotations

import argparse
import json
import os

from _util import record, run_isolated

CODE = """
import json, time, resource, statistics
from datetime import datetime, timedelta, timezone
import numpy as np, polars as pl
from safety.conflicts import ConflictConfig, conflict_candidates, height_and_rate, predict_conflicts
from tertiary.core.geo import LocalFrame
FRAME = LocalFrame(48.7, 2.4, 0.0)                # heights from WGS-84 geodesy (the system origin)

def traffic(n, box_m, epochs, seed=0):
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(-box_m / 2, box_m / 2, n), rng.uniform(-box_m / 2, box_m / 2, n),
                           rng.uniform(300.0, 12000.0, n)])
    spd, hdg = rng.uniform(70.0, 250.0, n), rng.uniform(0.0, 2 * np.pi, n)
    vz = np.where(rng.random(n) < 0.3, rng.choice([-1.0, 1.0], n) * rng.uniform(5.0, 15.0, n), 0.0)
    # heights and vertical rates are geodetic: place each aircraft at its height above the ground
    # point (x, y) and fly it along its local horizontal (+ vz along its local up), so "level"
    # means level in height, not in ENU z (which curves away by ρ²/2R)
    lat, lon, _ = FRAME.to_geodetic(pos[:, 0], pos[:, 1], np.zeros(n))
    pos = np.column_stack(FRAME.from_geodetic(lat, lon, pos[:, 2]))
    _, _, up = height_and_rate(pos, np.zeros_like(pos), FRAME)
    vh = np.column_stack([np.sin(hdg), np.cos(hdg), np.zeros(n)])
    vh -= np.einsum("ij,ij->i", vh, up)[:, None] * up
    vel = spd[:, None] * vh / np.linalg.norm(vh, axis=1)[:, None] + vz[:, None] * up
    sp = rng.uniform(50.0, 150.0, n)
    sv = rng.uniform(2.0, 8.0, n)
    sig = np.column_stack([sp, sp, 1.5 * sp, sv, sv, 0.5 * sv])
    corr = np.eye(6)
    for a in range(3):
        corr[a, a + 3] = corr[a + 3, a] = 0.5          # position–velocity correlation of a tracker
    cov = (sig[:, :, None] * corr[None] * sig[:, None, :]).reshape(n, 36)
    t0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
    frames = []
    for k in range(epochs):
        p = pos + vel * 5.0 * k
        frames.append(pl.DataFrame({{
            "run": np.zeros(n, np.uint32), "epoch": [t0 + timedelta(seconds=5 * k)] * n,
            "track_id": np.arange(n, dtype=np.uint64),
            "x_m": p[:, 0], "y_m": p[:, 1], "z_m": p[:, 2],
            "vx_mps": vel[:, 0], "vy_mps": vel[:, 1], "vz_mps": vel[:, 2],
        }}).with_columns(pl.col("epoch").cast(pl.Datetime("us", "UTC")),
                        pl.Series("cov", cov, dtype=pl.Array(pl.Float64, 36)),
                        pl.lit("bench").alias("method")))
    return frames

frames = traffic({n}, {box_m}, {epochs})
cfg = ConflictConfig(mode="{mode}")
predict_conflicts(frames[0].head(200), cfg, frame=FRAME)                    # warm-up
rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
if "{what}" == "epoch":
    times, cand, rows, alerts, slim = [], [], [], [], []
    for _ in range({repeat}):
        for f in frames:
            t = time.perf_counter()
            out = predict_conflicts(f, cfg, frame=FRAME)
            times.append(time.perf_counter() - t)
            rows.append(out.height)
            alerts.append(int(out["alert"].sum()))
            slim.append(int((out["alert"] | out["near"]).sum()))
    screen = []
    for f in frames:
        t = time.perf_counter()
        i, j = conflict_candidates(f, cfg, frame=FRAME)
        screen.append(time.perf_counter() - t)
        cand.append(len(i))
    res = {{"s_per_epoch_best": min(times), "s_per_epoch_median": statistics.median(times),
           "screen_s_median": statistics.median(screen), "candidate_pairs_per_epoch": statistics.mean(cand),
           "output_rows_per_epoch": statistics.mean(rows), "alerts_per_epoch": statistics.mean(alerts),
           "slim_rows_per_epoch": statistics.mean(slim)}}
else:
    allf = pl.concat(frames)
    t = time.perf_counter()
    out_all = predict_conflicts(allf, cfg, frame=FRAME)
    res = {{"s_per_epoch_batch": (time.perf_counter() - t) / len(frames), "batch_rows": out_all.height}}
res["rss_after_setup_mib"] = rss_before
print(json.dumps(res))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--aircraft", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--epochs", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--modes", nargs="+", default=["corrected", "seed"])
    ap.add_argument("--box-km", type=float, default=200.0)
    ap.add_argument("--density", action="store_true", help="also run boxes growing with sqrt(N)")
    args = ap.parse_args()
    n_ref = min(args.aircraft)
    cases = [("fixed_box", n, args.box_km * 1e3) for n in args.aircraft]
    if args.density:
        cases += [("constant_density", n, args.box_km * 1e3 * (n / n_ref) ** 0.5) for n in args.aircraft if n != n_ref]
    results = []
    load_before = os.getloadavg()
    for mode in args.modes:
        for kind, n, box in cases:
            kw = dict(n=n, box_m=box, epochs=args.epochs, repeat=args.repeat, mode=mode)
            r = run_isolated(CODE.format(what="epoch", **kw))
            bt = run_isolated(CODE.format(what="batch", **kw))
            r.update({"mode": mode, "layout": kind, "aircraft": n, "box_km": box / 1e3,
                      "per_epoch_call_rss_mib": r["peak_rss_mib"] - r["rss_after_setup_mib"],
                      "s_per_epoch_batch": bt["s_per_epoch_batch"], "batch_rows": bt["batch_rows"],
                      "batch_call_rss_mib": bt["peak_rss_mib"] - bt["rss_after_setup_mib"],
                      "peak_rss_mib_batch": bt["peak_rss_mib"]})
            results.append(r)
            print(json.dumps(r))
    payload = {
        "scenario": {"epochs": args.epochs, "repeat": args.repeat, "traffic": "random terminal-like, heights 300-12000 m",
                     "config": "ConflictConfig() defaults (terminal 3 NM / 1000 ft, T = 105 s, covariance thresholds at clip(T_min, 0, T), same-time rule, near margins 1 NM / 300 ft), geodetic heights (frame 48.7N 2.4E)"},
        "results": results,
        "targets": {"s_per_epoch_10000": 0.5},
        # the machine is shared: 1-min load averages before and after (2 cores → > 2 means contention)
        "load_average_before_after": [load_before[0], os.getloadavg()[0]],
    }
    path = record("bench_conflicts", payload)
    print(json.dumps(payload, indent=2))
    print(f"recorded in {path}")


if __name__ == "__main__":
    main()
