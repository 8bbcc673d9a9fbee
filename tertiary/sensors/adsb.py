"""ADS-B as a sensor (``radars.kind == "adsb"``): a ground station's reports of the positions
aircraft broadcast, fused like any other source.

An ADS-B report is a Cartesian plot, like an MLAT one (:mod:`tertiary.sensors.mlat`): the
broadcast WGS-84 position in the station's local ENU frame (``plot_x_m``, ``plot_y_m``), placed
at its barometric altitude. Its accuracy is what the aircraft declares:

* **NACp** (navigation accuracy category, position; DO-260B) states the estimated position
  uncertainty EPU, a 95 % bound on the horizontal error. For a circular Gaussian error the
  radial 95 % point is k σ with k = √(−2 ln 0.05) = 2.448, so per axis

      σ_x = σ_y = EPU(NACp) / 2.448,    σ_xy = 0                                        (ADSB-1)

  A report that states its own ``plot_sigma_x_m`` / ``plot_sigma_y_m`` keeps them; one that
  states neither σ nor NACp gets the station's nominal ``sigma_range_m``.
* **NIC** (integrity containment) and **SIL** (source integrity level) say whether the position
  can be trusted at all. A report below :class:`AdsbQuality`'s minima is not fused: alignment
  sends it to ``rejects`` with the failing indicator as the reason (NACp 0 or any indicator
  below its minimum; a missing indicator is not a failure, as recordings without it are common).

The reference built from ADS-B has its own, stricter quality filter
(:class:`tertiary.evaluation.reference.ReferenceConfig`, NACp ≥ 8 by default).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray

__all__ = ["ADSB", "AdsbQuality", "K95_2D", "NACP_EPU95_M", "QUALITY_COLUMNS", "REFERENCE_MIN_NACP",
           "REFERENCE_MIN_NIC", "fusion_rejects", "sigma_from_nacp",
           "station_rows"]

#: the ``radars.kind`` of an ADS-B ground station
ADSB = "adsb"
#: the quality indicators an ADS-B report may carry (integers; null = not broadcast)
QUALITY_COLUMNS = ("adsb_nacp", "adsb_nic", "adsb_sil")
#: NACp → estimated position uncertainty, 95 % horizontal bound (m) (DO-260B); NACp 0 = unknown
NACP_EPU95_M = {11: 3.0, 10: 10.0, 9: 30.0, 8: 92.6, 7: 185.2, 6: 555.6, 5: 926.0, 4: 1852.0,
                3: 3704.0, 2: 7408.0, 1: 18520.0}
#: radial 95 % point of a circular Gaussian in units of its per-axis σ, (ADSB-1)
K95_2D = float(np.sqrt(-2.0 * np.log(0.05)))
#: the default quality of an ADS-B point used as the reference (truth): NACp 8 = EPU < 0.05 NM;
#: NIC not required (:class:`tertiary.evaluation.reference.ReferenceConfig`, the ASTERIX import)
REFERENCE_MIN_NACP = 8
REFERENCE_MIN_NIC = 0


@dataclass(frozen=True)
class AdsbQuality:
    """The minimum quality of an ADS-B report that is fused.

    ``min_nacp`` 5: EPU < 0.5 NM (926 m), about the accuracy of an en-route radar at 100 NM;
    ``min_nic`` 1: a containment radius is declared (NIC 0 = unknown integrity);
    ``min_sil`` 1: the source's probability of exceeding it is bounded (SIL 0 = unknown).
    """

    min_nacp: int = 5
    min_nic: int = 1
    min_sil: int = 1


def sigma_from_nacp(nacp: ArrayLike) -> NDArray[np.float64]:
    """(ADSB-1) per-axis σ (m) of each NACp; NaN for 0, null or out of range."""
    q = np.asarray(nacp, float)
    table = np.full(12, np.nan)
    for k, v in NACP_EPU95_M.items():
        table[k] = v / K95_2D
    ok = np.isfinite(q) & (q >= 0) & (q <= 11)
    out = np.full(q.shape, np.nan)
    out[ok] = table[q[ok].astype(np.int64)]
    return out


def station_rows(reports: pl.DataFrame, radars: pl.DataFrame) -> NDArray[np.bool_]:
    """Per report: whether its sensor is an ADS-B ground station."""
    if "kind" not in radars.columns or reports.height == 0:
        return np.zeros(reports.height, bool)
    ids = radars.filter(pl.col("kind") == ADSB)["radar_id"].cast(pl.Int64).to_numpy()
    return np.isin(reports["radar_id"].cast(pl.Int64).to_numpy(), ids)


def fusion_rejects(reports: pl.DataFrame, radars: pl.DataFrame, quality: AdsbQuality) -> NDArray[np.object_]:
    """Per report: the reason an ADS-B report is below ``quality`` and is not fused, or None
    (other sensors' rows, reports without the indicators, good reports)."""
    out = np.full(reports.height, None, object)
    adsb_rows = station_rows(reports, radars)
    if not adsb_rows.any():
        return out
    for col, name, lo in (("adsb_sil", "SIL", quality.min_sil), ("adsb_nic", "NIC", quality.min_nic),
                          ("adsb_nacp", "NACp", max(quality.min_nacp, 1))):
        if col not in reports.columns:
            continue
        v = reports[col].cast(pl.Float64).fill_null(np.nan).to_numpy()
        bad = adsb_rows & np.isfinite(v) & (v < lo)
        texts = np.array([f"ADS-B quality below the fusion minimum ({name} {k} < {lo})" for k in range(lo)], object)
        out[bad] = texts[np.clip(v[bad], 0, lo - 1).astype(np.int64)]
    return out
