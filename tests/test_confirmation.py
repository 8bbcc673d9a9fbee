"""Alert confirmation (safety.confirmation): m of the last n picture epochs, batch = step fold."""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np
import polars as pl
import pytest

from safety.confirmation import ConfirmState, confirm_alerts, confirm_step, epoch_index

T0 = datetime(2021, 10, 7, 12, 0, 0)


def _conflicts(rows):
    return pl.DataFrame(rows, schema={"run": pl.UInt32, "epoch": pl.Datetime("us"), "method": pl.String,
                                      "id_a": pl.UInt64, "id_b": pl.UInt64, "alert": pl.Boolean}, orient="row")


def _grid(n_epochs, methods=("m",), runs=(0,)):
    pic = pl.DataFrame([(r, T0 + timedelta(seconds=4 * k), m) for r in runs for m in methods for k in range(n_epochs)],
                       schema={"run": pl.UInt32, "epoch": pl.Datetime("us"), "method": pl.String}, orient="row")
    return epoch_index(pic)


def test_a_one_epoch_blip_never_alerts_and_a_persistent_condition_does_after_m_epochs():
    flags = [False, True, False, False, True, True, True, True]
    c = _conflicts([(0, T0 + timedelta(seconds=4 * k), "m", 1, 2, f) for k, f in enumerate(flags)])
    out = confirm_alerts(c, _grid(len(flags)), 3, 4)
    assert out["raw_alert"].to_list() == flags
    # epoch 1 alone: no; epochs 4,5: 1 and 2 of the last 4; epoch 6: 3 of 4 -> alert
    assert out["alert"].to_list() == [False, False, False, False, False, False, True, True]


def test_missing_rows_count_as_no_condition_on_the_picture_grid():
    # condition at grid epochs 0, 1 and 3; the pair has no row at epoch 2 (not even near)
    c = _conflicts([(0, T0 + timedelta(seconds=4 * k), "m", 1, 2, True) for k in (0, 1, 3)])
    assert confirm_alerts(c, _grid(4), 3, 3)["alert"].to_list() == [False, False, False]
    assert confirm_alerts(c, _grid(4), 3, 4)["alert"].to_list() == [False, False, True]


def test_one_of_one_is_the_raw_condition():
    c = _conflicts([(0, T0, "m", 1, 2, True), (0, T0, "m", 1, 3, False)])
    assert confirm_alerts(c, _grid(1), 1, 1)["alert"].to_list() == [True, False]


@pytest.mark.parametrize("seed", range(5))
def test_batch_rule_equals_the_step_function_folded_over_epochs(seed):
    rng = np.random.default_rng(seed)
    n_ep, m, n = 40, int(rng.integers(1, 4)), 4
    rows = []
    for run in (0, 1):
        for meth in ("a", "b"):
            for k in range(n_ep):
                for a, b in ((1, 2), (1, 3), (2, 3)):
                    if rng.random() < 0.6:
                        rows.append((run, T0 + timedelta(seconds=4 * k), meth, a, b, bool(rng.random() < 0.5)))
    c = _conflicts(rows).sort("run", "epoch", "method", "id_a", "id_b")
    grid = _grid(n_ep, ("a", "b"), (0, 1))
    batch = confirm_alerts(c, grid, m, n)
    state, got = ConfirmState(), []
    for k in range(n_ep):
        part = c.filter(pl.col("epoch") == T0 + timedelta(seconds=4 * k)).rename({"alert": "raw_alert"})
        state, flags = confirm_step(state, part, m, n)
        got.append(part.with_columns(flags))
    folded = pl.concat(got).sort("run", "epoch", "method", "id_a", "id_b")
    assert folded["alert"].to_list() == batch["alert"].to_list()
    assert batch["alert"].sum() > 0 and (batch["raw_alert"] & ~batch["alert"]).sum() > 0


def test_bad_m_of_n_is_refused():
    with pytest.raises(ValueError):
        confirm_alerts(_conflicts([]), _grid(1), 3, 2)
