"""Exceptions the engine raises for things a user can fix (or chose to stop)."""


class InputError(ValueError):
    """The input cloud or an option is unusable; the message says why in plain words."""


class Cancelled(RuntimeError):
    """The caller's cancel event was set; nothing was changed."""


class ModelNotFoundError(FileNotFoundError):
    """No weights at the given path, or no shipped default model yet."""


class ModelMismatchError(ValueError):
    """A weights file does not match its JSON config (names the mismatch)."""


def positive_number(value, message: str) -> float:
    """value as a finite float above 0, or an InputError with `message` (a format string
    given the value's repr as {!r})."""
    import math

    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not (math.isfinite(number) and number > 0):
        raise InputError(message.format(value))
    return number


def user_message(exc: BaseException) -> str | None:
    """The plain message of an error the user can fix or chose (None: an internal error).

    Both front ends add their context: the operators a hint about the panel, the command line
    the file name.
    """
    if isinstance(exc, (InputError, Cancelled, ModelNotFoundError, ModelMismatchError)):
        return str(exc)
    return None
