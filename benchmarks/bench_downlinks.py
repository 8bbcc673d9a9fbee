"""What the measured noise of the downlinked registers does to the tracks and the safety net.

Each dataset is run with the CLI, each run in a fresh process: with the configured σ of the
downlinked ground velocity and vertical rate, and with ``--measure-downlinks`` (the σ measured
from the recording's replies); the national peak also with each radar's biases removed first
(``tertiary register --method multi``: radar to radar by Mode S, no reference; then
``--register``). From each run's database, for the production tracker
picture:

* the σ the run used (its notes);
* horizontal RMSE, and the evaluation's NEES means (3-D position, 6-D state);
* per flight phase of the truth (straight, turn, climb, descent): the median 2-D horizontal
  position NEES and horizontal velocity NEES of the confirmed tracks against the nearest
  aircraft at the epoch (within 1 km; χ²₂'s median is 1.39), the median velocity σ and error;
* alert episodes: false, nuisance, picture-induced false, missed losses.

    python benchmarks/bench_downlinks.py [--only national15,default] [--work DIR]

Results: ``benchmarks/results/bench_downlinks.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import each_dataset  # noqa: E402
from bench_memory import CONFIGS  # noqa: E402
from bench_trust import _child, _national15  # noqa: E402

DATASETS = ("national15", "default")
VARIANTS = {"configured": [], "measured": ["--measure-downlinks"]}
#: on the national peak also with each radar's bias and clock offset removed first (``tertiary
#: register --method multi``, then ``--register``): the fused plots' errors are then closer to white
REGISTERED = {"registered": ["--register"], "registered+measured": ["--register", "--measure-downlinks"]}
#: the picture whose tracks are read: production's
PICTURE = ("information", "imm_sym")
SAFETY = ("false_alerts", "nuisance_alerts", "false_alerts_picture_induced", "missed_los")


def consistency(db: Path, method: str = PICTURE[0], flt: str = PICTURE[1]) -> dict:
    """Per truth phase: medians of the 2-D position NEES, the horizontal velocity NEES, the
    velocity σ (√ of the larger of P_vxvx, P_vyvy) and the velocity error, of the confirmed
    tracks against the nearest aircraft at each epoch (within 1 km)."""
    import duckdb
    import polars as pl
    from scipy.spatial import cKDTree
    con = duckdb.connect(str(db), read_only=True)
    q = lambda sql: pl.from_arrow(con.sql(sql).to_arrow_table())      # noqa: E731
    tr = q(f"select epoch, x_m, y_m, vx_mps, vy_mps, cov_ut from tracks where method = '{method}' "
           f"and filter = '{flt}' and status = 'confirmed'")
    truth = q("select time as epoch, x_m, y_m, vx_mps, vy_mps, segment from truth")
    con.close()
    truth = truth.filter(pl.col("epoch").is_in(tr["epoch"].unique().implode()))
    parts = []
    # a k-d tree per epoch: the nearest aircraft of every track at once
    for (epoch,), rows in tr.group_by(["epoch"]):
        at = truth.filter(pl.col("epoch") == epoch)
        if not at.height:
            continue
        d, i = cKDTree(at.select("x_m", "y_m").to_numpy()).query(rows.select("x_m", "y_m").to_numpy())
        near = at[i]
        parts.append(rows.with_columns(pl.Series("d", d), near["x_m"].alias("tx"), near["y_m"].alias("ty"),
                                       near["vx_mps"].alias("tvx"), near["vy_mps"].alias("tvy"),
                                       near["segment"].alias("phase")))
    a = pl.concat(parts).filter(pl.col("d") < 1000.0)
    iu = np.triu_indices(6)
    p = np.zeros((a.height, 6, 6))
    p[:, iu[0], iu[1]] = np.stack(a["cov_ut"].to_numpy())
    p = p + np.triu(p, 1).transpose(0, 2, 1)
    ep = np.column_stack([(a["x_m"] - a["tx"]).to_numpy(), (a["y_m"] - a["ty"]).to_numpy()])
    ev = np.column_stack([(a["vx_mps"] - a["tvx"]).to_numpy(), (a["vy_mps"] - a["tvy"]).to_numpy()])
    nees = lambda e, m: np.einsum("bi,bij,bj->b", e, np.linalg.inv(m), e)     # noqa: E731
    a = a.with_columns(pl.Series("pos_nees", nees(ep, p[:, :2, :2])), pl.Series("vel_nees", nees(ev, p[:, 3:5, 3:5])),
                       pl.Series("vel_sigma", np.sqrt(np.maximum(p[:, 3, 3], p[:, 4, 4]))),
                       pl.Series("vel_error", np.hypot(ev[:, 0], ev[:, 1])))
    out = a.group_by("phase").agg(pl.len().alias("rows"), *(pl.col(c).median().round(3) for c in (
        "pos_nees", "vel_nees", "vel_sigma", "vel_error"))).sort("phase")
    return {r.pop("phase"): r for r in out.iter_rows(named=True)}


def figures(db: Path) -> dict:
    import duckdb
    con = duckdb.connect(str(db), read_only=True)
    picture = "+".join(PICTURE)
    metrics = dict(con.sql(f"select metric, value from metrics where stage = 'tracker' and method = '{picture}' "
                           "and segment = 'all' and "
                           "metric in ('rmse_horizontal_m', 'nees_mean', 'nees6_mean')").fetchall())
    safety = dict(con.sql(f"select metric, value from metrics where method = '{picture}' and segment = 'all' and "
                          f"metric in {tuple(SAFETY)}").fetchall())
    notes = json.loads(dict(con.sql("select key, value from run").fetchall()).get("notes", "[]"))
    con.close()
    return {"notes": [n for n in notes if n.startswith("tracker: downlinked")],
            "tracker": {k: round(v, 3) for k, v in metrics.items()}, "safety": safety, "phases": consistency(db)}


def run_dataset(name: str, work: Path) -> dict:
    data = work / name
    if name == "national15":
        sim, args = _national15(work, name), CONFIGS["production"]
    else:
        sim, args = ["terminal-area"], []
    _child(["simulate", *sim, "--out", str(data), "--force", "--quiet"])
    out = {"simulate": sim, "run_args": args}
    variants = dict(VARIANTS)
    if name == "national15":
        _child(["register", str(data), "--method", "multi"])
        variants.update(REGISTERED)
    for variant, extra in variants.items():
        run = work / f"{name}-{variant}"
        wall, _ = _child(["run", str(data), "--out", str(run), "--force", "--no-report", "--tables", "full",
                          *args, *extra])
        out[variant] = {"run_s": round(wall, 1), **figures(run / "results.duckdb")}
        print(name, variant, json.dumps(out[variant]["tracker"]), json.dumps(out[variant]["safety"]), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(DATASETS))
    ap.add_argument("--work", type=Path, default=None, help="keep the datasets and runs here (default: a temp dir)")
    args = ap.parse_args()
    each_dataset("bench_downlinks", args.only, DATASETS, args.work, run_dataset, picture="+".join(PICTURE))

if __name__ == "__main__":
    main()
