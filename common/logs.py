"""Logging set-up and the one progress-bar factory every command uses."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeVar

from rich.console import Console
from rich.logging import RichHandler
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

T = TypeVar("T")

_LEVELS = {-1: logging.ERROR, 0: logging.WARNING, 1: logging.INFO}


def setup_logging(verbosity: int = 0, daemon: bool = False, info: bool | None = None) -> None:
    """Configure the root logger once.

    `verbosity` is -v minus -q: 0 shows warnings, 1 info, 2 or more debug, -1 or less errors
    only. Commands that log info by default (`info`; daemons always) start one step up: -v
    changes nothing there, -q drops to warnings. Daemons use plain timestamped lines (they end
    up in files and journals); interactive commands use rich.
    """
    if daemon if info is None else info:
        verbosity = max(verbosity, 1) if verbosity >= 0 else verbosity + 1
    level = _LEVELS.get(max(verbosity, -1), logging.DEBUG)
    if daemon:
        handler: logging.Handler = logging.StreamHandler()
        handler.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
        )
    else:
        # stderr, so that logs never mix into machine-readable output such as `--json`.
        handler = RichHandler(
            console=Console(stderr=True), show_path=False, rich_tracebacks=False, markup=False
        )
        handler.setFormatter(logging.Formatter("%(message)s"))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level)


def log_to_file(path: str | Path) -> Path:
    """Also write every log line (timestamped, info and up) to `path` (a daemon's run log)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    return path


def make_progress(transient: bool = False, disable: bool = False) -> Progress:
    """A rich progress display with the columns every cpslam bar shows.

    `{task.fields[info]}` carries free text (fps, loss) updated through
    `progress.update(task, info=...)`.
    """
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        transient=transient,
        disable=disable,
    )


def progress(
    iterable: Iterable[T] | None = None,
    total: int | None = None,
    desc: str = "",
    disable: bool = False,
) -> Iterator[T]:
    """Iterate with a progress bar: `for x in progress(items, desc="render"): ...`."""
    items = iterable if iterable is not None else range(total or 0)
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    with make_progress(disable=disable) as bar:
        task = bar.add_task(desc, total=total, info="")
        for item in items:
            yield item
            bar.advance(task)
