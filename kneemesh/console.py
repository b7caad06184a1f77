"""Terminal output for the command line and the benchmarks, readable in a terminal and in a pipe.

Rich sizes its output to the terminal; printed into a pipe (a CI log, ``| tee``) it falls back
to 80 columns and cuts table cells short, and its live progress bars print nothing until
they end.  Here, output that is not a terminal gets a wide console, and progress becomes one
plain line per event, so a long step shows that it is alive.
"""

from __future__ import annotations

import contextlib
import time
from typing import Callable, Iterator

from rich.console import Console

#: Width of a console that is not a terminal: wide enough for every table printed here.
PIPE_WIDTH = 320


def console(stderr: bool = False) -> Console:
    """A console on stdout (or stderr): the terminal's width, or :data:`PIPE_WIDTH` in a pipe."""
    probe = Console(stderr=stderr)
    return probe if probe.is_terminal else Console(stderr=stderr, width=PIPE_WIDTH, soft_wrap=False)


@contextlib.contextmanager
def step_progress(con: Console) -> Iterator[Callable[[str, str], None]]:
    """A ``progress(name, state)`` callback: a live spinner line per name in a terminal; elsewhere a
    plain line per change of state, with the seconds since that name started."""
    if con.is_terminal:
        from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

        with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=con) as bar:
            tasks: dict[str, int] = {}

            def live(name: str, state: str) -> None:
                if name not in tasks:
                    tasks[name] = bar.add_task(f"{name}: {state}", total=1)
                bar.update(tasks[name], description=f"{name}: {state}",
                           completed=0 if state == "running" else 1)

            yield live
        return
    started: dict[str, float] = {}

    def lines(name: str, state: str) -> None:
        if state == "running":
            started[name] = time.monotonic()
            con.print(f"{name}: running", highlight=False)
        else:
            took = time.monotonic() - started.get(name, time.monotonic())
            con.print(f"{name}: {state} ({took:.1f} s)", highlight=False)

    yield lines
