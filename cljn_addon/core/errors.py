"""Exceptions the engine raises for things a user can fix (or chose to stop)."""


class InputError(ValueError):
    """The input cloud or an option is unusable; the message says why in plain words."""


class Cancelled(RuntimeError):
    """The caller's cancel event was set; nothing was changed."""


class ModelNotFoundError(FileNotFoundError):
    """No weights at the given path, or no shipped default model yet."""


class ModelMismatchError(ValueError):
    """A weights file does not match its JSON config (names the mismatch)."""
