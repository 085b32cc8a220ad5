"""Typed errors. Library code raises these; only the CLI turns them into one line and exit 1."""


class Mcl3dError(Exception):
    """Base class: the message names what is wrong and what to do about it, in the problem's
    words. `setting` names the request field that would fix it (e.g. "gt_topic", "force"):
    the CLI appends the matching flag, so the library never speaks of flags."""

    def __init__(self, message: str, *, setting: str | None = None) -> None:
        super().__init__(message)
        self.setting = setting


class BackendUnavailable(Mcl3dError):
    """The requested compute backend cannot be started on this machine."""


class InputError(Mcl3dError):
    """An input file or parameter is missing, malformed or inconsistent."""


class LogFormatError(InputError):
    """A log file is not readable as the format it claims to be (corrupt, truncated, wrong type)."""


class TopicError(InputError):
    """A needed topic is missing or ambiguous in a log."""


class PointCloudError(InputError):
    """A point cloud message or file lacks what is needed (fields, points)."""


class TrajectoryError(InputError):
    """A trajectory file is malformed or does not cover what it must."""


class OutputExistsError(Mcl3dError):
    """An output exists and overwriting was not allowed."""


class MapError(Mcl3dError):
    """A map file is invalid, or a map does not fit its capacity."""


class ConfigError(InputError):
    """A configuration value is impossible or unknown."""


class RunInterrupted(Mcl3dError):
    """The user pressed Ctrl-C; what was finished has been written. The CLI exits with 130."""
