"""The command line: thin commands over the library's functions (one module per command group).

:mod:`~tertiary.cli.commands` holds the typer ``app`` and registers the commands of
:mod:`~tertiary.cli.simulate`, :mod:`~tertiary.cli.dataset`, :mod:`~tertiary.cli.run`,
:mod:`~tertiary.cli.results` and :mod:`~tertiary.cli.asterix`, which share
:mod:`~tertiary.cli.common`; :mod:`~tertiary.cli.main` is the entry that configures the
allocator before it loads them.
"""
