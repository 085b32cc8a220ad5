"""Typed errors. Library code raises these; only the CLI turns them into one line and exit 1."""


class Mcl3dError(Exception):
    """Base class: the message names what is wrong and what to do about it."""


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
    """An output exists and --force was not given."""


class MapError(Mcl3dError):
    """A map file is invalid, or a map does not fit its capacity."""


class ConfigError(InputError):
    """A configuration value is impossible or unknown."""


class RunInterrupted(Mcl3dError):
    """The user pressed Ctrl-C; what was finished has been written. The CLI exits with 130."""
