"""A picture and its truth as Stone Soup objects, so that Stone Soup's metric generators (OSPA,
GOSPA, SIAP, …) run on a ``tertiary`` run.

State vectors follow Stone Soup's constant-velocity convention, (x, vx, y, vy, z, vz) in the
local ENU frame (m, m/s): measure positions with ``Euclidean(mapping=POSITION_MAPPING)``. The
truth is interpolated at the picture's epochs
(:func:`tertiary.evaluation.matching.reference_at_epochs`, the reference the evaluation uses),
so track and truth states share time stamps, as Stone Soup's track-to-truth metrics need.
"""

from __future__ import annotations

from typing import Any

import polars as pl

from tertiary.evaluation.matching import reference_at_epochs

__all__ = ["to_stonesoup", "POSITION_MAPPING", "VELOCITY_MAPPING"]

#: indices of the position / velocity in the state vectors :func:`to_stonesoup` makes
POSITION_MAPPING = (0, 2, 4)
VELOCITY_MAPPING = (1, 3, 5)

_ORDER = ("x_m", "vx_mps", "y_m", "vy_mps", "z_m", "vz_mps")


def _stonesoup() -> Any:
    """Stone Soup's types, imported on first use; a clear error without the ``bench`` extra."""
    try:
        from stonesoup.types import groundtruth, state, track
    except ImportError as exc:
        raise ImportError("tertiary.interop.to_stonesoup needs Stone Soup: pip install 'tertiary[bench]'") from exc
    return state.State, track.Track, groundtruth.GroundTruthState, groundtruth.GroundTruthPath


def _one_run(frame: pl.DataFrame, run: int | None, what: str) -> pl.DataFrame:
    if "run" not in frame.columns:
        return frame
    if run is not None:
        return frame.filter(pl.col("run") == run)
    if frame["run"].n_unique() > 1:
        raise ValueError(f"{what} holds several runs: give run=")
    return frame


def _paths(frame: pl.DataFrame, id_col: str, state_type: Any, path_type: Any, prefix: str = "") -> list:
    """One path of ``path_type`` per ``id_col``, its states of ``state_type`` in time order."""
    out = []
    cols = [f"{prefix}{c}" for c in _ORDER]
    for (ident,), rows in frame.sort(id_col, "epoch").partition_by(id_col, as_dict=True, maintain_order=True).items():
        vectors = rows.select(cols).to_numpy()
        states = [state_type(v.reshape(-1, 1), timestamp=t) for v, t in zip(vectors, rows["epoch"].to_list())]
        out.append(path_type(states, id=str(ident)))
    return out


def to_stonesoup(picture: pl.DataFrame, truth: pl.DataFrame, run: int | None = None) -> tuple[list, list]:
    """(tracks, truths): one Stone Soup ``Track`` per ``track_id`` of ``picture`` (one picture's
    rows in the ``tracks`` schema) and one ``GroundTruthPath`` per aircraft of ``truth`` (the
    ``truth`` schema) alive at the picture's epochs, its states the truth at those epochs.
    Ids are the ``track_id`` / ``truth_id`` as strings. ``run``: the run to take when the
    frames hold several."""
    state, track, truth_state, truth_path = _stonesoup()
    if "method" in picture.columns and picture["method"].n_unique() > 1:
        raise ValueError("picture holds several pictures (column method): give one")
    pic = _one_run(picture, run, "picture")
    epochs = pic.select(pl.col("run") if "run" in pic.columns else pl.lit(0, pl.UInt32).alias("run"), "epoch")
    ref = _one_run(truth, run, "truth")
    at = reference_at_epochs(epochs, ref.drop("run") if "run" in ref.columns else ref)
    return (_paths(pic, "track_id", state, track),
            _paths(at, "truth_id", truth_state, truth_path, prefix="true_"))
