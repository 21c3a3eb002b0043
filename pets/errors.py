"""The error a user's configuration raises, in a module of its own so that run directories, video and the tools
can catch it without importing the whole configuration hub (:mod:`pets.config` re-exports it)."""

__all__ = ["ConfigError"]


class ConfigError(ValueError):
    """A configuration value or key the user gave is not accepted; the message says what is."""
