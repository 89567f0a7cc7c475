"""Errors raised by the engine. Callers catch `SenFuNetError`; bad input is also a `ValueError`."""


class SenFuNetError(Exception):
    """Base class of every error the engine raises on purpose."""


class InputError(SenFuNetError, ValueError):
    """An argument has the wrong shape, dtype or value; nothing was changed."""
