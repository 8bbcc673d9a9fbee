"""The command line: thin commands over the library's functions (one module per command group).

:mod:`~tertiary.cli.commands` holds the typer ``app`` and registers the commands of
:mod:`~tertiary.cli.simulate`, :mod:`~tertiary.cli.dataset`, :mod:`~tertiary.cli.run`,
:mod:`~tertiary.cli.results` and :mod:`~tertiary.cli.asterix`, which share
:mod:`~tertiary.cli.common`; :mod:`~tertiary.cli.main` is the ``python -m`` entry.
"""

from tertiary.core.memory import configure_allocator

# First, before anything here imports polars: jemalloc reads its setting once, when polars loads.
# Any entry to the command line (the console script, ``python -m tertiary.cli[.main]``, a test's
# ``from tertiary.cli import app``) runs this package's __init__ before the command modules.
configure_allocator()

from tertiary.cli.commands import app  # noqa: E402  (after the allocator is configured)

__all__ = ["app"]
