"""The one error a failed playback ends with."""

from __future__ import annotations

import traceback

from stgs.client.config import PlaybackError


class InternalError(PlaybackError):
    """A failure no part of the player expected (a defect, or a resource the machine ran out of); `detail` holds
    the traceback for the playback log."""

    def __init__(self, exc: BaseException):
        super().__init__(f"playback failed unexpectedly: {type(exc).__name__}: {str(exc)[:300] or '(no message)'} "
                         "(details in the playback log)")
        self.detail = "".join(traceback.format_exception(exc))


def playback_failure(failed: BaseExceptionGroup) -> BaseException:
    """The one error a failed task group ends the playback with: a PlaybackError a task raised, else an
    interruption (KeyboardInterrupt, SystemExit) as is, else any other error as an InternalError."""
    leaves = []

    def flatten(group: BaseExceptionGroup) -> None:
        for exc in group.exceptions:
            flatten(exc) if isinstance(exc, BaseExceptionGroup) else leaves.append(exc)

    flatten(failed)
    for kind in (PlaybackError, KeyboardInterrupt, SystemExit):
        for exc in leaves:
            if isinstance(exc, kind):
                return exc
    return InternalError(leaves[0])
