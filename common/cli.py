"""The command-line grammar shared by `cpslam`, `cpslam-agent` and `cpslam-server`.

One place for what every command has in common, so that a flag means the same everywhere
(docs/cli.md is the reference): the exit codes, `-v/--verbose`, `-q/--quiet` and `--version`
(accepted before or after a subcommand, added to every command by `App`), the `--json`,
`--overwrite` and `--out` options, and the overwrite rule (`check_output`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from enum import IntEnum
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from typer.core import TyperCommand, TyperGroup

__all__ = ["App", "ExitCode", "JsonOpt", "OverwriteOpt", "check_output", "fail",
           "interruptible", "out_option", "signal_handler", "stop_on_signals", "verbosity"]

logger = logging.getLogger(__name__)


class ExitCode(IntEnum):
    """Exit status of every cpslam command (docs/cli.md)."""

    OK = 0
    ERROR = 1
    """The command started but failed: a child process died, a time-out, no endpoint."""
    USAGE = 2
    """Bad arguments or inputs, found before any work (also click's own usage errors)."""
    NO_SERVER = 3
    """No cpslam-server answered in time."""
    UNACKNOWLEDGED = 4
    """cpslam-agent: the server did not acknowledge everything in time."""
    REFUSED = 5
    """cpslam-agent: the server refused this agent incarnation (the id streams already;
    restart with --resume or a new id)."""
    INTERRUPTED = 130
    """Stopped by Ctrl-C or SIGTERM (128 + SIGINT, the shell's convention)."""


JsonOpt = Annotated[
    bool, typer.Option("--json", help="Print machine-readable JSON to stdout instead of text.")
]
OverwriteOpt = Annotated[
    bool, typer.Option("--overwrite", help="Replace outputs that already exist (else exit 2).")
]


def out_option(help: str) -> Any:
    """The `--out/-o` option (an output file or folder); only its help differs by command."""
    return typer.Option("--out", "-o", help=help)


def fail(message: str, code: ExitCode = ExitCode.USAGE) -> NoReturn:
    """Print `error: message` to stderr and exit with `code`."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(int(code))


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """SIGINT and SIGTERM set the yielded event (the loop stops after its current step and
    writes what it did); a second signal exits at once with `ExitCode.INTERRUPTED`. The
    previous handlers come back on exit. Main thread only (Python's rule for handlers)."""
    stop = threading.Event()
    handler = signal_handler(stop, window_s=0.0, action="stopping after this frame")
    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def interruptible(fn: Callable[[], Any], what: str) -> Any:
    """`fn()` on a worker thread, so that SIGINT/SIGTERM never raise inside it: an exception
    raised asynchronously inside a C extension's import or call (matplotlib, Open3D) can
    abort the interpreter at exit. A signal logs that `what` was interrupted and exits at
    once with `ExitCode.INTERRUPTED`, skipping interpreter clean-up: only for work that
    holds nothing to save (a report of outputs already written). Off the main thread, where
    Python allows no handlers, `fn` simply runs."""
    if threading.current_thread() is not threading.main_thread():
        return fn()
    done = threading.Event()
    outcome: dict[str, Any] = {}

    def work() -> None:
        try:
            outcome["value"] = fn()
        except BaseException as err:  # noqa: BLE001 - re-raised on the calling thread
            outcome["error"] = err
        finally:
            done.set()

    def handler(signum: int, _frame: object) -> None:
        logger.warning("%s: %s interrupted, exiting", signal.Signals(signum).name, what)
        for h in logging.getLogger().handlers:
            h.flush()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(int(ExitCode.INTERRUPTED))

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        threading.Thread(target=work, name=what, daemon=True).start()
        done.wait()  # a lock wait that signal handlers interrupt (POSIX)
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
    if "error" in outcome:
        raise outcome["error"]
    return outcome.get("value")


def signal_handler(stop: threading.Event, *, window_s: float, action: str,
                   clock: Callable[[], float] = time.monotonic
                   ) -> Callable[[int, object], None]:
    """A handler whose first signal sets `stop` (logging `action`); the same signal within
    `window_s` of it is ignored (one request delivered twice); any other later signal exits
    with `ExitCode.INTERRUPTED`."""
    first: list[tuple[int, float]] = []

    def handler(signum: int, _frame: object) -> None:
        name, now = signal.Signals(signum).name, clock()
        if not first:
            first.append((signum, now))
            logger.info("%s: %s (send it again to exit at once)", name, action)
            stop.set()
            return
        signum0, t0 = first[0]
        if signum == signum0 and now - t0 < window_s:
            logger.info("%s again %.2f s after the first: the same request (delivered to the "
                        "process group too?); still %s", name, now - t0, action)
            return
        logger.warning("second %s: exiting at once", name)
        raise SystemExit(ExitCode.INTERRUPTED)

    return handler


def check_output(path: Path, overwrite: bool) -> None:
    """The overwrite rule: an existing file or non-empty folder at `path` is an error (exit 2,
    before any work) unless `overwrite`."""
    exists = path.is_file() or (path.is_dir() and any(path.iterdir()))
    if exists and not overwrite:
        fail(f"{path} already exists; pass --overwrite to replace it")


_VERBOSITY = "cpslam.verbosity"


def verbosity(ctx: typer.Context | None) -> int:
    """-v minus -q counted over the whole command line (0 without a command line)."""
    return ctx.meta.get(_VERBOSITY, 0) if ctx is not None else 0


def _count(sign: int) -> Any:
    def callback(ctx: typer.Context, value: int) -> None:
        # Context.meta is shared by a command and its subcommands, so `cpslam -v run -v`
        # adds up; logging is set again after each so a late flag still takes effect.
        from cpslam.common.logs import setup_logging

        ctx.meta[_VERBOSITY] = ctx.meta.get(_VERBOSITY, 0) + sign * (value or 0)
        setup_logging(ctx.meta[_VERBOSITY])

    return callback


def _version(ctx: typer.Context, value: bool) -> None:
    if value and not ctx.resilient_parsing:
        from importlib.metadata import PackageNotFoundError, version

        try:
            text = version("cpslam")
        except PackageNotFoundError:  # a source tree that was never installed
            text = "unknown"
        typer.echo(f"cpslam {text}")
        raise typer.Exit(int(ExitCode.OK))


def _shared(
    verbose: Annotated[int, typer.Option(
        "--verbose", "-v", count=True, expose_value=False, show_default=False, callback=_count(+1),
        help="More log output (-vv: debug).")] = 0,
    quiet: Annotated[int, typer.Option(
        "--quiet", "-q", count=True, expose_value=False, show_default=False, callback=_count(-1),
        help="Less log output (warnings, or errors only).")] = 0,
    version: Annotated[bool, typer.Option(
        "--version", expose_value=False, is_eager=True, callback=_version,
        help="Print the version and exit.")] = False,
) -> None:
    """The options every command accepts, wherever they appear on the command line."""


def _shared_params() -> list[Any]:
    # Built by typer itself from `_shared`'s signature, as for any command's options.
    probe = typer.Typer(add_completion=False)
    probe.command()(_shared)
    return list(typer.main.get_command(probe).params)


class _Command(TyperCommand):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.params.extend(_shared_params())


class _Group(TyperGroup):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.params.extend(_shared_params())


class App(typer.Typer):
    """A `typer.Typer` whose commands and groups all take the shared options, with `-h`,
    no shell-completion commands, and help when called without arguments."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("cls", _Group)
        kwargs.setdefault("add_completion", False)
        kwargs.setdefault("context_settings", {"help_option_names": ["-h", "--help"]})
        super().__init__(**kwargs)

    def command(self, *args: Any, **kwargs: Any) -> Any:
        kwargs.setdefault("cls", _Command)
        return super().command(*args, **kwargs)
