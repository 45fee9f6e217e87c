"""An exception as a user reads it: ``"ValueError: the message"``, not Python's repr
(``ValueError('the message')``), in log lines, ``metrics.json`` and campaign rows."""

from __future__ import annotations


def error_text(exc: BaseException) -> str:
    """``"TypeName: message"``, or the type's name alone when the message is empty."""
    message = str(exc).strip()
    return f"{type(exc).__name__}: {message}" if message else type(exc).__name__
