"""The ``tertiary`` command's entry (the console script and ``python -m tertiary.cli.main``).

The allocator is configured before the commands are loaded: jemalloc, polars' allocator, reads
its setting once, when polars is first imported, and the command modules import polars. So the
commands are imported by name after :func:`~tertiary.core.memory.configure_allocator` has run,
and importing this module changes nothing in the process.
"""

from __future__ import annotations

import importlib

from tertiary.core.memory import configure_allocator


def main() -> None:  # pragma: no cover
    """Run the ``tertiary`` command on ``sys.argv``."""
    configure_allocator()
    importlib.import_module("tertiary.cli.commands").app()


if __name__ == "__main__":  # pragma: no cover
    main()
