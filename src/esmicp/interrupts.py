"""Ctrl-C stays a ``KeyboardInterrupt`` through compiled code.

An extension function that calls back into Python while a Ctrl-C is pending can end in
``SystemError: ... returned a result with an exception set``, with the ``KeyboardInterrupt`` only
in its cause chain; a caller's ``except Exception`` then swallows the user's interrupt (measured
with the earlier JIT-compiled kernels: ``esmicp bench`` ignored 4 of 8 interrupts).
:func:`keeps_keyboard_interrupt` turns such an error back into the ``KeyboardInterrupt`` it is;
the library's entry points (:func:`esmicp.register`, :func:`esmicp.methods.local.refine`) carry
it. (The compiled kernels of :mod:`esmicp._kernels` raise the ``KeyboardInterrupt`` itself.)
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

_P = ParamSpec("_P")
_R = TypeVar("_R")


def caused_by_interrupt(error: BaseException) -> bool:
    """True when ``error`` is a ``KeyboardInterrupt`` or has one in its cause / context chain."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


def keeps_keyboard_interrupt(function: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator: a ``SystemError`` caused by a ``KeyboardInterrupt`` is raised as that interrupt
    (the signature, and so the types, of ``function`` kept)."""

    @functools.wraps(function)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        try:
            return function(*args, **kwargs)
        except SystemError as error:
            if caused_by_interrupt(error):
                raise KeyboardInterrupt from None
            raise

    return wrapper
