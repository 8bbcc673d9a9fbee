"""``python -m tertiary.cli``: the ``tertiary`` command."""

from tertiary.cli.main import main

main()
