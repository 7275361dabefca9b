"""Rich progress bars on stderr for the long commands (publish, verify, gates).

The core functions take a ``progress(event, info)`` callback (``drivetrack.release.publish_release``,
``drivetrack.release.verify_release``, ``drivetrack.gates.run_gates``); this module turns their
events into one bar. A ``planned`` event sizes the bar (``bytes`` or ``steps``); ``uploaded`` and
``checked`` events advance it by their ``bytes``, every other event by one step.
"""
from __future__ import annotations

import threading
from contextlib import contextmanager

__all__ = ["progress_bar"]


def _console():
    """The console bars are drawn on (stderr; rich draws nothing live when it is not a terminal)."""
    from rich.console import Console

    return Console(stderr=True)


@contextmanager
def progress_bar(label: str, *, unit: str = "bytes", enabled: bool = True):
    """Yield a ``progress(event, info)`` callback that draws one bar named ``label``.

    ``unit``: ``"bytes"`` (size from ``planned``'s ``bytes``, advanced by events' ``bytes``) or
    ``"steps"`` (size from ``planned``'s ``steps``, advanced by one per event). With
    ``enabled=False`` (``--json``) or when stderr is not a terminal the callback does nothing; the
    bar appears at the first event. Safe to call from worker threads.
    """
    if unit not in ("bytes", "steps"):
        raise ValueError(f"progress unit {unit!r}: expected 'bytes' or 'steps'")
    console = _console() if enabled else None
    if console is None or not console.is_terminal:  # --json, or logs/CI: no bar, no partial lines
        yield lambda event, info: None
        return
    from rich.progress import (BarColumn, DownloadColumn, MofNCompleteColumn, Progress, TextColumn,
                               TimeElapsedColumn, TransferSpeedColumn)

    columns = [TextColumn(f"[bold]{label}"), BarColumn()]
    columns += ([DownloadColumn(), TransferSpeedColumn()] if unit == "bytes" else [MofNCompleteColumn()])
    columns.append(TimeElapsedColumn())
    lock = threading.Lock()
    state: dict = {}  # the bar starts at the first event (so an unreachable store prints no empty bar)

    def progress(event: str, info: dict) -> None:
        with lock:
            if "bar" not in state:
                state["bar"] = Progress(*columns, console=console, transient=False)
                state["bar"].start()
                state["task"] = state["bar"].add_task(label, total=None)
            bar, task = state["bar"], state["task"]
            if event == "planned":
                bar.update(task, total=info.get(unit))
            elif unit == "bytes":
                if event in ("uploaded", "checked"):
                    bar.advance(task, int(info.get("bytes") or 0))
            else:
                bar.advance(task, 1)

    try:
        yield progress
    finally:
        if "bar" in state:
            state["bar"].stop()
