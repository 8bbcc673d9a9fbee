"""``python -m tertiary.cli.main``: the ``tertiary`` command (the app is :data:`tertiary.cli.commands.app`;
importing :mod:`tertiary.cli` configures the allocator first)."""

from tertiary.cli import app


def main() -> None:  # pragma: no cover
    """Run the ``tertiary`` command on ``sys.argv``."""
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
