"""The stage clock of a run: each stage's time and peak memory, and the progress callback."""

from __future__ import annotations

import time
from collections.abc import Callable

from tertiary.runtime.windows import peak_rss_mib

__all__ = ["Progress", "StageClock"]

#: what a run says as it goes (a stage's name, a window's line)
Progress = Callable[[str], None]


class StageClock:
    """Each stage's time (summed over windows) and the peak memory reached by its end; says a
    stage's name when it first starts."""

    def __init__(self, say: Progress):
        self.say, self.timings, self._t = say, {}, time.perf_counter()
        self.name: str | None = None
        self.memory: dict[str, float] = {}
        #: "finalize:" once the whole-run stages start (their memory is told apart from the windows')
        self.prefix = ""

    def stage(self, name: str | None, say: bool = True) -> None:
        """Start stage ``name`` (None: stop). A stage's time adds up over windows; its name is
        said the first time only (a window says one line of its own, :class:`tertiary.runtime.windows.Meter`),
        never with ``say=False`` (the engine's own reading and writing of each window).
        The peak resident memory reached by the end of a stage is kept in ``memory``."""
        now = time.perf_counter()
        if self.name is not None:
            key = f"{self.name}_s"
            self.timings[key] = self.timings.get(key, 0.0) + now - self._t
            # re-inserted: the record lists the stages in the order they last ended, so its
            # peaks-so-far read in increasing order even for a stage met again (write_tables)
            self.memory.pop(self.prefix + self.name, None)
            self.memory[self.prefix + self.name] = round(peak_rss_mib(), 1)
        self.name, self._t = name, now
        if say and name and f"{name}_s" not in self.timings and name != getattr(self, "_said", None):
            self._said = name
            self.say(name)
