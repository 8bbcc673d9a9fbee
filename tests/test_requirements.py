"""Requirements TOML, its validation, and verdicts with their confidence."""

from __future__ import annotations

from dataclasses import replace as dataclass_replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from scipy import stats

from tertiary.core.errors import DataError
from tertiary.evaluation.requirements import (Requirement, Requirements, check_requirements, example_path, load_requirements, metric_kind)


def _metrics(rows: list[tuple[str, str, str, float]], stage: str = "evaluation") -> pl.DataFrame:
    return pl.DataFrame({"stage": [stage] * len(rows), "method": [r[0] for r in rows], "metric": [r[1] for r in rows],
                         "segment": [r[2] for r in rows], "value": [float(r[3]) for r in rows],
                         "n_runs": pl.Series([1] * len(rows), dtype=pl.UInt32)})


def _one(table: pl.DataFrame, req: str, method: str = "p") -> dict:
    row = table.filter((pl.col("requirement") == req) & (pl.col("method") == method))
    assert row.height == 1
    return row.row(0, named=True)


def test_example_file_loads_and_names_its_values_examples():
    reqs = load_requirements(example_path())
    assert {r.metric for r in reqs.items} >= {"rmse_horizontal_m", "prob_update", "false_tracks_per_hour",
                                              "id_changes_per_hour"}
    assert "NOT QUOTATIONS" in example_path().read_text(encoding="utf-8")
    enr = next(r for r in reqs.items if r.name == "H-RMS-ENR")
    assert (enr.threshold, enr.op, enr.breakdown) == (500.0, "<=", "all")
    assert reqs.confidence == 0.95


@pytest.mark.parametrize("text, key", [
    ('[[requirement]]\nname="a"\nmetric="rmse_horizontal_m"\nthresh=5\n', "requirement[0].thresh"),
    ('[[requirement]]\nname="a"\nmetric="rmse_horizontal_m"\nthreshold="5"\n', "requirement[0].threshold"),
    ('[[requirement]]\nname="a"\nmetric="rmse_horizontal_m"\nthreshold=5\nop="<"\n', "requirement[0].op"),
    ('[[requirement]]\nname="a"\nmetric="prob_update"\nthreshold=97\n', "requirement[0].threshold"),
    ('[[requirement]]\nname="a"\nthreshold=5\n', "requirement[0].metric"),
    ('[settings]\nconfidence=1.0\n[[requirement]]\nname="a"\nmetric="x"\nthreshold=1\n', "settings.confidence"),
    ('[[requirement]]\nname="a"\nmetric="x"\nthreshold=1\n[[requirement]]\nname="a"\nmetric="y"\nthreshold=1\n',
     "requirement[1].name"),
    ('[settings]\nconfidence=0.9\n', "requirement"),
    ('[[requirement]\nname=', "not valid TOML"),
])
def test_bad_file_is_a_data_error_naming_file_and_key(tmp_path: Path, text: str, key: str):
    path = tmp_path / "req.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(DataError) as exc:
        load_requirements(path)
    assert str(path) in str(exc.value) and key in str(exc.value)


def test_missing_file_is_a_data_error(tmp_path: Path):
    with pytest.raises(DataError, match="cannot read"):
        load_requirements(tmp_path / "nope.toml")


def test_rms_verdict_uses_the_chi_square_bound():
    met = _metrics([("p", "rmse_horizontal_m", "all", 100.0), ("p", "n_points", "all", 10_000.0),
                    ("q", "rmse_horizontal_m", "all", 100.0), ("q", "n_points", "all", 100.0),
                    ("r", "rmse_horizontal_m", "all", 120.0), ("r", "n_points", "all", 1e6)])
    reqs = Requirements(items=(Requirement("A", "rmse_horizontal_m", 105.0),
                               Requirement("B", "rmse_horizontal_m", 103.0)))
    out = check_requirements(met, reqs)
    bound = 100.0 * np.sqrt(1000 / stats.chi2.ppf(0.05, 1000))      # 10 000 samples / 10 per independent
    assert _one(out, "A")["bound"] == pytest.approx(bound) and 103.0 < bound < 105.0
    assert _one(out, "A")["verdict"] == "pass"
    assert _one(out, "B")["verdict"] == "insufficient"                # point passes, bound does not
    assert _one(out, "A", "q")["verdict"] == "insufficient"           # 10 independent samples < 30
    assert _one(out, "A", "r")["verdict"] == "fail"
    assert _one(out, "A")["n_samples"] == 10_000.0


def test_proportion_verdict_uses_the_wilson_bound():
    met = _metrics([("p", "prob_update", "all", 0.99), ("p", "n_update_intervals", "all", 100.0),
                    ("q", "prob_update", "all", 0.99), ("q", "n_update_intervals", "all", 10_000.0),
                    ("r", "prob_update", "all", 0.95), ("r", "n_update_intervals", "all", 10_000.0)])
    out = check_requirements(met, Requirements(items=(Requirement("P", "prob_update", 0.97, op=">="),)))
    z, p, n = stats.norm.ppf(0.95), 0.99, 100.0
    wilson = (p + z * z / (2 * n) - z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))) / (1 + z * z / n)
    assert _one(out, "P")["bound"] == pytest.approx(wilson)
    # the Wilson bound is close to the exact Clopper–Pearson one (99 of 100)
    assert _one(out, "P")["bound"] == pytest.approx(stats.beta.ppf(0.05, 99, 2), abs=0.01)
    assert [_one(out, "P", m)["verdict"] for m in "pqr"] == ["insufficient", "pass", "fail"]


def test_rate_verdict_uses_the_poisson_bound_and_missing_metric_is_insufficient():
    met = _metrics([("p", "false_tracks_per_hour", "all", 0.0), ("p", "picture_hours", "all", 1.0),
                    ("q", "false_tracks_per_hour", "all", 0.0), ("q", "picture_hours", "all", 4.0),
                    ("r", "false_tracks_per_hour", "all", 2.0), ("r", "picture_hours", "all", 4.0)])
    reqs = Requirements(items=(Requirement("F", "false_tracks_per_hour", 1.0),
                               Requirement("T", "rmse_horizontal_m", 150.0, breakdown="range:0-50km"),
                               Requirement("O", "false_tracks_per_hour", 1.0, method="absent")))
    out = check_requirements(met, reqs)
    assert _one(out, "F")["bound"] == pytest.approx(-np.log(0.05))   # 0 events in 1 h: 2.996 / h
    assert [_one(out, "F", m)["verdict"] for m in "pqr"] == ["insufficient", "pass", "fail"]
    assert _one(out, "T")["value"] is None and _one(out, "T")["verdict"] == "insufficient"
    assert _one(out, "O", "absent")["verdict"] == "insufficient"
    assert set(out.columns[:7]) == {"requirement", "metric", "breakdown", "threshold", "value", "n_samples", "verdict"}


def test_metric_kinds():
    assert [metric_kind(m) for m in ("rmse_height_m", "across_track_rms_m", "p99_horizontal_m", "pd",
                                     "mode_s_correct_frac", "id_changes_per_hour", "latency_s")] == \
        ["rms", "rms", "quantile", "proportion", "proportion", "rate", "point"]


def test_a_run_with_a_bad_requirements_file_fails_before_its_first_window(tmp_path: Path, monkeypatch):
    """The requirements are read when the run starts: a bad file stops it before any window is
    processed (on a day's recording, not after hours), and a good one is read once, not again
    at the end. Fails if the file is read only by the end's evaluation."""
    from tertiary import pipeline
    from tertiary.pipeline import scoring, streaming
    from tertiary.simulate import load_scenario, simulate
    base = load_scenario("terminal-area")
    ds = simulate(base.replace(runs=1, seed=5, duration_s=180.0, traffic=dataclass_replace(base.traffic, aircraft=6)))
    steps: list[int] = []
    monkeypatch.setattr(streaming, "process_step", lambda *a, f=streaming.process_step, **k:
                        steps.append(1) or f(*a, **k))
    bad = tmp_path / "bad.toml"
    bad.write_text("[[requirement]]\nname = 'x'\nmetric = 'rmse_horizontal_m'\nthreshold = 'high'\n")
    cfg = pipeline.PipelineConfig(methods=("information",), filters=(), centralized=False, requirements_file=str(bad))
    with pytest.raises(DataError, match="threshold"):
        pipeline.run(ds, tmp_path / "run", cfg, window_s=60.0)
    assert steps == []
    reads: list[str] = []
    monkeypatch.setattr(scoring, "load_requirements", lambda p, f=load_requirements: reads.append(str(p)) or f(p))
    pipeline.run(ds, tmp_path / "good", dataclass_replace(cfg, requirements_file=str(example_path())), window_s=60.0)
    assert steps and reads == [str(example_path())]
