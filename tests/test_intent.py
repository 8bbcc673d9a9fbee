"""A track withholds a selected or cleared level its aircraft has left (tertiary.stages.tracking.intent)."""

from datetime import datetime, timedelta

import polars as pl
import pytest

from tertiary.pipeline.config import PipelineConfig
from tertiary.pipeline.streaming import _identity_step, init_stream_state
from tertiary.stages.tracking.intent import reached_column, withhold_left_levels

KEYS = ["run", "filter", "method", "track_id"]
T0 = datetime(2021, 10, 7, 8, 52)
LEVEL = 7646.8


def _track(track_id: int, alts: list[float], rates: list[float], levels: list[float | None],
           column: str = "selected_alt_m") -> pl.DataFrame:
    n = len(alts)
    return pl.DataFrame({"run": [0] * n, "filter": ["imm_sym"] * n, "method": ["information"] * n,
                         "track_id": [track_id] * n, "epoch": [T0 + timedelta(seconds=4 * k) for k in range(n)],
                         "alt_m": alts, "alt_rate_mps": rates, column: levels},
                        schema_overrides={"run": pl.UInt32, "track_id": pl.UInt64, column: pl.Float64})


def _published(tracks: pl.DataFrame, column: str = "selected_alt_m") -> list[float | None]:
    out, _ = withhold_left_levels(tracks, tracks.select(KEYS).clear(), KEYS, [column])
    return out.sort("epoch")[column].to_list()


def test_a_descent_from_the_selected_level_withholds_it_until_a_new_one_comes():
    # level 4 m below its selected level, then the descent's onset while the old selection is
    # still the latest read: held there, the prediction would keep the aircraft level
    alts = [7642.9, 7642.9, 7642.9, 7642.9, 7621.0, 7578.0, 7535.0]
    rates = [0.0, 0.01, -0.02, 0.0, -5.4, -10.1, -10.7]
    levels = [LEVEL, LEVEL, LEVEL, LEVEL, LEVEL, LEVEL, 916.8]
    assert _published(_track(1, alts, rates, levels)) == [LEVEL] * 4 + [None, None, 916.8]


def test_a_capture_that_overshoots_keeps_its_level():
    # descending onto the selected level, the tracked height passes it with the rate still high:
    # the track was never level there, so the level stays (the prediction's capture tolerance)
    alts = [7760.0, 7705.0, 7660.0, 7640.0, 7638.0]
    rates = [-14.0, -12.0, -6.0, -3.0, -0.5]
    assert _published(_track(2, alts, rates, [LEVEL] * 5)) == [LEVEL] * 5


def test_a_track_returning_to_its_level_publishes_it_again():
    # reached, left upwards (a bust), then descending back towards it
    alts = [7646.0, 7646.0, 7700.0, 7760.0, 7730.0, 7690.0]
    rates = [0.0, 0.0, 6.0, 4.0, -6.0, -8.0]
    assert _published(_track(3, alts, rates, [LEVEL] * 6)) == [LEVEL, LEVEL, None, None, LEVEL, LEVEL]


def test_a_cleared_level_is_withheld_like_a_selected_one():
    alts, rates = [2000.0, 2000.0, 1980.0], [0.0, 0.0, -5.0]
    assert _published(_track(4, alts, rates, [2000.0] * 3, "cleared_alt_m"), "cleared_alt_m") == [2000.0, 2000.0, None]


@pytest.mark.parametrize("split", range(1, 7))
def test_the_rule_gives_the_same_rows_whatever_the_window(split):
    tracks = pl.concat([
        _track(1, [7642.9, 7642.9, 7642.9, 7621.0, 7578.0, 7535.0, 7500.0], [0.0, 0.0, 0.0, -5.4, -10.1, -10.7, -10.7],
               [LEVEL] * 6 + [916.8]),
        _track(2, [7760.0, 7705.0, 7660.0, 7640.0, 7638.0, 7638.0, 7610.0], [-14.0, -12.0, -6.0, -3.0, -0.5, 0.0, -6.0],
               [LEVEL] * 7)])
    whole = _published_all(tracks, [tracks])
    cut = T0 + timedelta(seconds=4 * split)
    windows = [tracks.filter(pl.col("epoch") < cut), tracks.filter(pl.col("epoch") >= cut)]
    assert _published_all(tracks, windows) == whole


def _published_all(tracks: pl.DataFrame, windows: list[pl.DataFrame]) -> list:
    state = tracks.select(KEYS).clear()
    out = []
    for w in windows:
        rows, reached = withhold_left_levels(w, state, KEYS, ["selected_alt_m"])
        # carried as the pipeline carries it: the tracks seen in this window replace their entries
        state = pl.concat([state.join(reached, on=KEYS, how="anti"), reached], how="diagonal_relaxed")
        out.append(rows)
    assert reached_column("selected_alt_m") in state.columns
    return pl.concat(out).sort("track_id", "epoch")["selected_alt_m"].to_list()


def test_the_pipeline_carries_a_reached_level_into_the_next_window():
    # level at its selected level in one window, leaving it in the next: the carried identity
    # state must remember that the level was reached
    alts = [7642.9, 7642.9, 7642.9, 7621.0, 7578.0]
    rates = [0.0, 0.0, 0.0, -5.4, -10.1]
    tracks = _track(1, alts, rates, [LEVEL] * 5).drop("selected_alt_m").with_columns(
        pl.lit(7, pl.UInt64).alias("plot_target_id"))
    pictures = tracks.select("run", "epoch", "method", pl.col("plot_target_id").alias("target_id"),
                             pl.lit("4ca1b2").alias("mode_s"), pl.lit(LEVEL).alias("selected_alt_m"))
    state = init_stream_state(PipelineConfig()).identity
    cut = T0 + timedelta(seconds=12)
    out = []
    for part in (pl.col("epoch") < cut, pl.col("epoch") >= cut):
        rows, state = _identity_step(state, tracks.filter(part), pictures.filter(part))
        out.append(rows)
    assert pl.concat(out).sort("epoch")["selected_alt_m"].to_list() == [LEVEL] * 3 + [None, None]
