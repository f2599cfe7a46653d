"""User-facing errors.

Anything a user can cause with bad input (an unknown task, a corrupt run directory, a mismatched
checkpoint) raises a subclass of :class:`DvfbError`. The CLI turns these into a one-line message and
a non-zero exit instead of a traceback.
"""


class DvfbError(Exception):
    """Base class for errors caused by user input or run state, reported without a traceback."""


class ConfigError(DvfbError, ValueError):
    """An unknown option, an invalid value or an inconsistent configuration."""


class RunDirError(DvfbError):
    """A run directory is missing, incomplete, corrupt, or would be overwritten."""


class CheckpointError(DvfbError):
    """A checkpoint cannot be read, or belongs to another agent or configuration."""


class NonFiniteLossError(DvfbError, FloatingPointError):
    """A loss became NaN or inf; training stops and keeps the last good checkpoint."""


class RemoteError(DvfbError):
    """A remote service (the Hugging Face hub of ``dvfb push``) could not be reached or refused a
    request: a network error is one line, as any other, never a traceback."""


class RunInterrupted(DvfbError):
    """SIGTERM or SIGINT stopped a run after its current step; a checkpoint to resume from was
    written. The CLI exits with status 128 + the signal number, as a shell reports a signal."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum
