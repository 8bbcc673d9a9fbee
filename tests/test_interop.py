"""tertiary.interop: a picture and its truth as Stone Soup objects, imported only when used, and
the documented example (docs/examples/stonesoup_metrics.py) on a tiny run."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from datetime import datetime, timedelta, timezone
from pathlib import Path

import polars as pl
import pytest

from tertiary import RunStore
from tertiary.contract import TIME
from tertiary.interop import to_stonesoup

ROOT = Path(__file__).resolve().parents[1]
T0 = datetime(2024, 5, 1, 12, tzinfo=timezone.utc)
STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")


def _truth() -> pl.DataFrame:
    """Two aircraft sampled every 10 s: 1 from 0 to 20 s, 2 from 0 to 10 s."""
    rows = [(1, 0, 0.0), (1, 10, 1000.0), (1, 20, 2000.0), (2, 0, 5000.0), (2, 10, 5000.0)]
    return pl.DataFrame(rows, schema=["truth_id", "s", "x_m"], orient="row").select(
        "truth_id", (pl.lit(T0) + pl.duration(seconds="s")).cast(TIME).alias("time"), "x_m",
        pl.lit(0.0).alias("y_m"), pl.lit(3000.0).alias("z_m"), pl.lit(100.0).alias("vx_mps"),
        pl.lit(0.0).alias("vy_mps"), pl.lit(0.0).alias("vz_mps"))


def _picture(epochs_s: tuple[int, ...] = (5, 15), run: int = 0) -> pl.DataFrame:
    """Track 7 on aircraft 1 at ``epochs_s``, 20 m east of it."""
    return pl.DataFrame({"s": list(epochs_s)}).select(
        pl.lit(run, pl.UInt32).alias("run"), (pl.lit(T0) + pl.duration(seconds="s")).cast(TIME).alias("epoch"),
        pl.lit(7, pl.UInt64).alias("track_id"), pl.lit("information+singer").alias("method"),
        (pl.col("s") * 100.0 + 20.0).alias("x_m"), pl.lit(0.0).alias("y_m"), pl.lit(3000.0).alias("z_m"),
        pl.lit(100.0).alias("vx_mps"), pl.lit(0.0).alias("vy_mps"), pl.lit(0.0).alias("vz_mps"))


def test_importing_interop_does_not_import_stonesoup():
    code = "import sys, tertiary.interop; assert not [m for m in sys.modules if m.startswith('stonesoup')]"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_without_stonesoup_the_error_names_the_extra(monkeypatch):
    for name in ("stonesoup", "stonesoup.types"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(ImportError, match=r"tertiary\[bench\]"):
        to_stonesoup(_picture(), _truth())


def test_tracks_and_truth_at_the_picture_epochs():
    pytest.importorskip("stonesoup")
    from stonesoup.types.groundtruth import GroundTruthPath
    from stonesoup.types.track import Track

    tracks, truths = to_stonesoup(_picture(), _truth())
    assert [type(t) for t in tracks] == [Track] and all(type(t) is GroundTruthPath for t in truths)
    (track,) = tracks
    assert track.id == "7" and [s.timestamp for s in track] == [T0 + timedelta(seconds=5), T0 + timedelta(seconds=15)]
    # Stone Soup's order (x, vx, y, vy, z, vz)
    assert track[0].state_vector.ravel().tolist() == [520.0, 100.0, 0.0, 0.0, 3000.0, 0.0]
    by_id = {t.id: t for t in truths}
    # aircraft 1 interpolated at 5 and 15 s; aircraft 2 alive at 5 s only (its samples end at 10 s)
    assert [s.state_vector[0, 0] for s in by_id["1"]] == [500.0, 1500.0]
    assert [s.timestamp for s in by_id["2"]] == [T0 + timedelta(seconds=5)]


def test_several_runs_need_a_run():
    two = pl.concat([_picture(run=0), _picture(run=1)])
    with pytest.raises(ValueError, match="run="):
        to_stonesoup(two, _truth())
    pytest.importorskip("stonesoup")
    tracks, _ = to_stonesoup(two, _truth(), run=1)
    assert len(tracks) == 1 and len(tracks[0]) == 2


def _example():
    spec = importlib.util.spec_from_file_location("stonesoup_metrics", ROOT / "docs" / "examples" / "stonesoup_metrics.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_example_runs_on_a_tiny_run(tmp_path, capsys):
    pytest.importorskip("stonesoup")
    pic = _picture((0, 5, 10, 15, 20)).with_columns(pl.lit("information").alias("method"),
                                                      pl.lit("singer").alias("filter"))
    with RunStore.create(tmp_path) as store:
        store.write("tracks", pic)
        store.write("truth", _truth())
        store.write("metrics", pl.DataFrame({"stage": ["evaluation"], "method": ["information+singer"],
                                             "metric": ["ospa_m"], "segment": ["all"], "value": [10.0],
                                             "n_runs": [1]}))
    example = _example()
    name, series = example.ospa(tmp_path, c_m=1000.0, p=1.0)
    # at 0-10 s: the track 20 m from aircraft 1, aircraft 2 missed; at 15-20 s: aircraft 1 alone
    assert name == "information+singer" and [v for _, v in series] == pytest.approx([510.0] * 3 + [20.0] * 2)
    example.main([str(tmp_path)])
    assert "information+singer: 5 epochs" in capsys.readouterr().out
