"""One exception tree: every error guard raises on purpose is a GuardError."""


class GuardError(Exception):
    """Base of guard's own errors; the CLI prints its message on one line and exits non-zero."""


class ConfigError(GuardError):
    """A config file or scenario is unreadable, has an unknown key, a wrong type or an impossible value."""


class SourceError(GuardError):
    """An input (file, link, bus) cannot be opened or read."""
