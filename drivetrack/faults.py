"""Test-only fault injection: a real ``SIGKILL`` of an annotation worker process at a chosen point.

Nothing here runs unless ``DRIVETRACK_TEST_KILL_SEGMENT`` is set, and it only ever kills a worker
process started by :func:`drivetrack.annotate.annotate` (never the process that runs the command),
so the fault suite (``tests/test_hostile_annotate.py``) can check what a crashed worker leaves.

Environment:
    DRIVETRACK_TEST_KILL_SEGMENT: the segment whose worker dies.
    DRIVETRACK_TEST_KILL_AT: die at the N-th kill point reached in that worker (default 1). The
        kill point is inside the DriveTrack writer, after the clip's first video frame was
        written to its temporary ``.partial-*`` file.
    DRIVETRACK_TEST_KILL_ONCE: a file path; the worker dies only if the file does not exist yet
        (it creates it first), so the retry of the segment succeeds.
"""
from __future__ import annotations

import os
import signal

__all__ = ["KILL_SEGMENT_ENV", "KILL_AT_ENV", "KILL_ONCE_ENV", "enter_worker", "kill_point"]

KILL_SEGMENT_ENV = "DRIVETRACK_TEST_KILL_SEGMENT"
KILL_AT_ENV = "DRIVETRACK_TEST_KILL_AT"
KILL_ONCE_ENV = "DRIVETRACK_TEST_KILL_ONCE"

_in_worker = False
_reached = 0


def enter_worker() -> None:
    """Mark this process as an annotation worker (the only kind :func:`kill_point` may kill)."""
    global _in_worker, _reached
    _in_worker, _reached = True, 0


def kill_point(segment: str) -> None:
    """SIGKILL this worker process here when the environment asks for it (see the module doc)."""
    global _reached
    if not _in_worker or os.environ.get(KILL_SEGMENT_ENV) != segment:
        return
    _reached += 1
    if _reached != int(os.environ.get(KILL_AT_ENV) or 1):
        return
    once = os.environ.get(KILL_ONCE_ENV)
    if once:
        try:
            os.close(os.open(once, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return
    os.kill(os.getpid(), signal.SIGKILL)
