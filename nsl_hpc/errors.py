"""The one exception type for mistakes a user can fix (bad config, bad paths)."""


class ConfigError(ValueError):
    """A user-fixable mistake; its message is one line that names the bad value and what is allowed."""
