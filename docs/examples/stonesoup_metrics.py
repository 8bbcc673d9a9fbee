"""Stone Soup's OSPA on a ``tertiary`` run: one tracker picture and the truth, read from the
run's database, converted with :func:`tertiary.interop.to_stonesoup` and scored by a Stone Soup
``MultiManager`` with its ``OSPAMetric``.

    python docs/examples/stonesoup_metrics.py RUN_DIR [PICTURE]

PICTURE is a tracker picture's name, ``<fusion method>+<filter>`` (default: the first). Needs
Stone Soup (``pip install 'tertiary[bench]'``) and a run with a truth (a simulated dataset).
The run's own ``ospa_m`` (:mod:`tertiary.evaluation.multitarget`) is printed beside it.
"""

from __future__ import annotations

import sys
from datetime import datetime
from pathlib import Path

import polars as pl

from tertiary import RunStore
from tertiary.interop import POSITION_MAPPING, to_stonesoup

_NAME = "method || '+' || filter"


def load(run_dir: str | Path, picture: str | None = None, run: int = 0) -> tuple[str, pl.DataFrame, pl.DataFrame]:
    """(picture name, its rows of run ``run`` in the ``tracks`` table, the truth table)."""
    with RunStore.open(run_dir, read_only=True) as store:
        names = store.sql(f"SELECT DISTINCT {_NAME} AS name FROM tracks ORDER BY name")["name"].to_list()
        name = picture or names[0]
        tracks = store.sql("SELECT run, epoch, track_id, method, x_m, y_m, z_m, vx_mps, vy_mps, vz_mps "
                           f"FROM tracks WHERE {_NAME} = ? AND run = ?", [name, run])
        truth = store.read("truth")
    return name, tracks, truth


def ospa(run_dir: str | Path, picture: str | None = None, c_m: float = 1852.0,
         p: float = 2.0) -> tuple[str, list[tuple[datetime, float]]]:
    """(picture name, Stone Soup's OSPA at each of its epochs) of one tracker picture."""
    from stonesoup.measures import Euclidean
    from stonesoup.metricgenerator.manager import MultiManager
    from stonesoup.metricgenerator.ospametric import OSPAMetric

    name, tracks, truth = load(run_dir, picture)
    ss_tracks, ss_truths = to_stonesoup(tracks, truth)
    manager = MultiManager([OSPAMetric(c=c_m, p=p, measure=Euclidean(mapping=POSITION_MAPPING))])
    manager.add_data({"tracks": ss_tracks, "groundtruth_paths": ss_truths})
    metric = manager.generate_metrics()["ospa_generator"]["OSPA distances"]
    values = metric.value if isinstance(metric.value, list) else [metric]   # one epoch: a single metric
    return name, [(m.timestamp, float(m.value)) for m in values]


def main(argv: list[str]) -> None:
    run_dir = argv[0]
    name, series = ospa(run_dir, argv[1] if len(argv) > 1 else None)
    with RunStore.open(run_dir, read_only=True) as store:
        own = store.sql("SELECT value FROM metrics WHERE stage = 'evaluation' AND method = ? AND metric = 'ospa_m'",
                        [name])
    print(f"{name}: {len(series)} epochs, Stone Soup mean OSPA {sum(v for _, v in series) / len(series):.1f} m"
          + (f", tertiary ospa_m {own['value'][0]:.1f} m" if own.height else ""))


if __name__ == "__main__":
    main(sys.argv[1:])
