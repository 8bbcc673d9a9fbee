"""ASTERIX recordings in and out (docs/asterix.md): a reader of the pipeline's input beside
:mod:`tertiary.io.dataset`, and a writer of its inputs and pictures.

* :func:`import_recordings` / :func:`write_import` — pcap, pcapng or raw data blocks of CAT048,
  CAT001, CAT020 and CAT021 of ADS-B ground stations (reports; CAT020 of MLAT sensors), CAT034
  and CAT002 (antenna timing), other CAT021 (truth), CAT062 (external tracks) and CAT004 (STCA
  alerts) → a dataset.
* :func:`external_alerts` — the CAT004 STCA alerts of recordings as ``alerts`` rows (unscored).
* :func:`write_recording` — a dataset's reports (CAT048, CAT020, CAT021 by sensor kind), truth
  (CAT021) and scans (CAT034) as ``recording.ast`` + ``sites.toml``.
* :func:`export_picture` — a picture (``tracks`` schema) as CAT062 system tracks.
* :func:`export_alerts` — alert episodes (``alerts`` schema) as CAT004 STCA messages.
* :func:`read_sites` — the SAC/SIC → radar registry.

libasterix (the codec, ~2.4 s to import) and numba (the compiled CAT048 decoder) load only when
one of these is first used.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["import_recordings", "write_import", "write_recording", "export_picture", "read_sites", "external_alerts",
           "export_alerts"]

_WHERE = {"import_recordings": "dataset", "write_import": "dataset", "write_recording": "encode",
          "export_picture": "encode", "read_sites": "sites", "external_alerts": "dataset", "export_alerts": "encode"}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(f"tertiary.io.asterix.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'tertiary.io.asterix' has no attribute {name!r}")
