"""Error hierarchy: every expected failure is an MvtopError with a one-line message."""


class MvtopError(Exception):
    """Base of all errors the command line reports as one line and a non-zero exit.

    Messages name the file, topic or key at fault and what was expected, e.g.
    ``"log.mcap: topic '/contact' not found (expected std_msgs/msg/Bool)"``.
    """

    exit_code = 2


class ConfigError(MvtopError):
    """A YAML config is unreadable, has an unknown key, or a value of the wrong type or range."""


class LogError(MvtopError):
    """An MCAP log is unreadable, truncated, corrupt, or lacks a topic, frame or encoding."""


class MeshError(MvtopError):
    """A mesh file is missing, unreadable, empty, or geometrically unusable."""


class ModelError(MvtopError):
    """A segmentation model file is missing or does not have the expected signature."""


class EstimationError(MvtopError):
    """The estimator cannot run on the given inputs (e.g. no usable frame)."""


class TrackError(MvtopError):
    """A pose track (estimate output folder) is missing or malformed."""
