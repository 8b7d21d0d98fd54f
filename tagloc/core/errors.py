"""The one exception root of tagloc, and its one-line warnings.

Every error a user can cause (bad file, bad argument, missing system library) is raised as a
subclass of :class:`TaglocError`; the CLI turns it into a one-line message and an exit code.
Something odd but usable (a frame skipped, times made up) is a warning line: :func:`warn_stderr`.
"""

from __future__ import annotations

import sys


def warn_stderr(message: str) -> None:
    """One warning line on stderr, the form every layer writes them in: tagloc's default warning
    stream (the pipeline's outputs, a session read without frames.csv, a bag's skipped frames)."""
    print(f"tagloc: warning: {message}", file=sys.stderr, flush=True)


class TaglocError(Exception):
    """Root of all errors tagloc raises on purpose. ``exit_code`` is what the CLI returns."""

    exit_code = 2


class InputError(TaglocError):
    """A file or argument given by the user is malformed (the message names file and line)."""


class MapError(InputError):
    """A sticker map is malformed."""


class CalibrationError(InputError):
    """A camera calibration or rig file is malformed."""


class SessionError(InputError):
    """A session directory is missing required files or is malformed."""


class BackendUnavailable(TaglocError):
    """An optional backend (libdmtx, paho-mqtt, ...) cannot be used on this machine."""

    exit_code = 3


class SourceFailed(TaglocError):
    """A camera or stream failed during a run (unplugged, its reads failing): exit code 1, so that
    a supervisor restarting on failure restarts it, unlike a bad argument's 2."""

    exit_code = 1
