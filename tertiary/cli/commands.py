"""The ``tertiary`` command: the typer app, its one error boundary and its commands, in help order.

One error boundary (:class:`_Boundary`) turns every expected failure (:mod:`tertiary.core.errors`,
file-system errors) into one line on stderr and an exit code — 2 for a bad option, 3 for bad
input data, 4 for a refused allocation, 1 for an internal error — with the traceback only under
``tertiary --debug``.
"""

from __future__ import annotations

from typing import Annotated, Any

import typer
from typer.core import TyperGroup

from tertiary.cli import dataset, inspect, results, run, simulate
from tertiary.cli.asterix import export_app, import_app
from tertiary.cli.common import err_console, reset_output
from tertiary.core.errors import TertiaryError
from tertiary.core.memory import one_malloc_arena

try:
    from polars.exceptions import PanicException as _PANIC
except ImportError:  # pragma: no cover - older polars
    _PANIC = Exception


def _failure(exc: BaseException) -> tuple[int, str]:
    """Exit code and one-line message of an exception that reached the boundary."""
    if isinstance(exc, TertiaryError):
        return exc.exit_code, str(exc)
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        return 3, f"{where}{exc.strerror or exc}"
    if isinstance(exc, MemoryError):
        return 4, "out of memory (reduce the input or the number of methods/filters)"
    return 1, (f"internal error ({type(exc).__name__}: {exc}); "
               "run again with `tertiary --debug ...` for the traceback and report it")


class _Boundary(TyperGroup):
    """The one error boundary of every command (see the module docstring)."""

    def invoke(self, ctx: typer.Context) -> Any:
        try:
            return super().invoke(ctx)
        except (typer.TyperException, typer.Exit, typer.Abort):
            raise
        except KeyboardInterrupt:
            err_console.print("interrupted")
            raise typer.Exit(130) from None
        except (Exception, _PANIC) as exc:   # a Rust panic (polars) is a BaseException
            if (ctx.obj or {}).get("debug"):
                raise
            code, message = _failure(exc)
            err_console.print(f"error: {message}")
            raise typer.Exit(code) from None


app = typer.Typer(cls=_Boundary, add_completion=False, no_args_is_help=False, rich_markup_mode=None,
                  pretty_exceptions_enable=False, context_settings={"max_content_width": 120},
                  help="Tertiary processing of multi-radar surveillance data and safety evaluation.")


@app.callback()
def _root(ctx: typer.Context,
          debug: Annotated[bool, typer.Option("--debug", help="show the full traceback of an error")] = False) -> None:
    """Tertiary processing of multi-radar surveillance data and safety evaluation.

    Exit codes: 0 success, 1 internal error, 2 bad option, 3 bad input data or file, 4 refused
    (a limit would be exceeded). Add --debug before the command for a traceback."""
    ctx.obj = {"debug": debug}
    reset_output()                    # per invocation (run/simulate may change the progress mode)
    one_malloc_arena()                # the process is the command's: before any worker thread


app.command("simulate")(simulate.simulate)
app.command("validate")(dataset.validate)
app.command("run")(run.run)
app.command("register")(dataset.register)
app.command("evaluate")(run.evaluate)
app.command("report")(results.report)
app.command("sql")(results.sql)
app.command("episodes")(inspect.episodes)
app.command("compare")(inspect.compare)
app.command("scenarios")(simulate.scenarios)
app.add_typer(import_app, name="import")
app.add_typer(export_app, name="export")
