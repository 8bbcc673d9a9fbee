"""Interoperability with other tracking libraries: a ``tertiary`` picture and its truth as their
objects. Stone Soup (:func:`to_stonesoup`) is imported only when a conversion runs — importing
this package needs nothing beyond ``tertiary`` (Stone Soup comes with the ``bench`` extra)."""

from tertiary.interop.stonesoup import POSITION_MAPPING, VELOCITY_MAPPING, to_stonesoup

__all__ = ["to_stonesoup", "POSITION_MAPPING", "VELOCITY_MAPPING"]
