"""A Ctrl-C that reaches the run loop disguised as a stage's failure.

A SIGINT that lands while a numba function compiled with ``nogil=True`` runs (the depth stage's kernels)
comes out of the call as ``SystemError("CPUDispatcher(...) returned a result with an exception set")``, the
``KeyboardInterrupt`` as its cause. Caught as the stage's failure, the operator's stop would become one part's
ERROR and be lost: the run would go on.
"""
from __future__ import annotations


def raise_if_interrupted(exc: BaseException) -> None:
    """Raise ``KeyboardInterrupt`` (from ``exc``) where ``exc`` or an exception it was raised from or during
    is one; return otherwise."""
    seen: set[int] = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:
        if isinstance(link, KeyboardInterrupt):
            raise KeyboardInterrupt from exc
        seen.add(id(link))
        link = link.__cause__ or link.__context__
