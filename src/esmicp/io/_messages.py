"""Quoting file content in error messages: short, on one line, whatever the file holds."""

from __future__ import annotations

__all__ = ["MAX_MESSAGE_CHARS", "excerpt", "one_line"]

#: Longest problem description (after the path) an error message carries.
MAX_MESSAGE_CHARS = 240


def excerpt(text, limit: int = 40) -> str:
    """``repr`` of the first ``limit`` characters of ``text`` (``...`` marks a cut).

    For quoting words of a (possibly corrupt) file in an error message: the result is one line,
    and non-printable bytes show as escapes.
    """
    text = str(text)
    if len(text) <= limit:
        return repr(text)
    return repr(text[:limit]) + "..."


def one_line(problem: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``problem`` as one line of at most about ``limit`` characters (for third-party messages)."""
    lines = [line.strip() for line in str(problem).splitlines() if line.strip()]
    text = lines[0] if lines else ""
    if len(text) > limit:
        text = text[:limit].rstrip() + "..."
    return text
