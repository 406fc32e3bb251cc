"""The toolkit's error type: anything a user can cause (bad input, bad config, missing file)."""


class DockError(Exception):
    """A user-facing error: the CLI prints its message on one line and exits non-zero."""


class ConfigError(DockError, ValueError):
    """A configuration file or value is malformed (unknown key, wrong type, out of range)."""
