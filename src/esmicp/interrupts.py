"""Ctrl-C stays a ``KeyboardInterrupt`` through numba's compiled code.

A numba function that returns a new array calls back into Python to box it. A Ctrl-C that lands
in that call (the pending signal is raised there) comes out of the compiled function as
``SystemError: ... returned a result with an exception set``, with the ``KeyboardInterrupt`` only
in its cause chain; a caller's ``except Exception`` then swallows the user's interrupt (measured:
``esmicp bench`` ignored 4 of 8 interrupts). :func:`keeps_keyboard_interrupt` turns such an error
back into the ``KeyboardInterrupt`` it is; the library's entry points (:func:`esmicp.register`,
:func:`esmicp.methods.local.refine`) carry it.
"""

from __future__ import annotations

import functools


def caused_by_interrupt(error: BaseException) -> bool:
    """True when ``error`` is a ``KeyboardInterrupt`` or has one in its cause / context chain."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


def keeps_keyboard_interrupt(function):
    """Decorator: a ``SystemError`` caused by a ``KeyboardInterrupt`` is raised as that interrupt."""

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        try:
            return function(*args, **kwargs)
        except SystemError as error:
            if caused_by_interrupt(error):
                raise KeyboardInterrupt from None
            raise

    return wrapper
