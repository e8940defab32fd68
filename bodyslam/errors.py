"""The project's one exception family.

Every error a user can cause (bad file, bad option, bad input data) is a :class:`BodySlamError`; the CLIs turn it
into one line on stderr and exit code 1. Anything else escaping is a bug.
"""


class BodySlamError(Exception):
    """Base of every error the toolkit raises on purpose."""


class InputError(BodySlamError):
    """A file or value handed in by the user is missing, malformed or out of range (the message says where)."""


class ConfigError(BodySlamError):
    """A scenario, option or configuration value is invalid."""


class GeometryError(BodySlamError):
    """A geometric construction is impossible (e.g. a centre line that cannot be packed or a broken mesh)."""
