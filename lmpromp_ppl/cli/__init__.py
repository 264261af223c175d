"""The ``lmpromp`` command line (conventions in docs/cli.md).

Every command has ``--help``.  A user error prints one line to stderr and exits
with status 2, without a traceback.  Every ``--out`` refuses an existing target
unless ``--force``; ``--quiet`` silences progress; ``--seed`` fixes randomness.

Sub-command modules register themselves on :data:`app` (or add a typer
sub-application) in :func:`_register`.
"""

from __future__ import annotations

import sys

import typer

from lmpromp_ppl.errors import LmprompError

__all__ = ["app", "main"]

app = typer.Typer(
    name="lmpromp",
    help="Latent-Manifold ProMPs: fit, compare engines, predict, reproduce the thesis.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _register() -> None:
    import importlib

    for module in ("data", "fit", "compare", "predict", "reproduce", "bench", "sbc", "demo", "real_data", "timing"):
        try:
            importlib.import_module(f"lmpromp_ppl.cli.{module}")
        except ModuleNotFoundError as exc:
            if exc.name != f"lmpromp_ppl.cli.{module}":
                raise


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``lmpromp`` console script.

    A failed command leaves none of the directories it created empty behind
    (:func:`lmpromp_ppl.cli._common.remove_created_dirs`).
    """
    from lmpromp_ppl.cli._common import remove_created_dirs, start_recording, stop_recording

    _register()
    start_recording()
    status = 1
    try:
        status = _run(argv)
    finally:
        if status != 0:
            remove_created_dirs()
        else:
            stop_recording()
    return status


def _run(argv: list[str] | None) -> int:
    try:
        app(args=argv, standalone_mode=False)
    except LmprompError as exc:
        print(f"lmpromp: error: {exc}", file=sys.stderr)
        return 2
    except (FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        print(f"lmpromp: error: {exc}", file=sys.stderr)
        return 2
    except typer.Exit as exc:
        return exc.exit_code
    except typer.Abort:
        print("lmpromp: aborted", file=sys.stderr)
        return 1
    except Exception as exc:  # click usage errors
        # recent typer vendors its own click (typer._click), so match the
        # class by name rather than isinstance(exc, click.ClickException)
        if any(cls.__name__ == "ClickException" for cls in type(exc).__mro__):
            msg = exc.format_message().replace("\n", " ")
            print(f"lmpromp: error: {msg}", file=sys.stderr)
            return 2
        raise
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
