"""numba behind one decorator, and the one line a first run prints when it compiles.

Every compiled kernel of errplan is declared with :func:`njit` (numba's, with ``cache=True`` by default).
Compiled code is cached on disk beside the sources (numba's ``__pycache__``, or ``$NUMBA_CACHE_DIR``), so
a machine compiles each kernel once, on the first command that needs it. When numba looks an errplan
kernel up in that cache and misses, i.e. just before it compiles, errplan prints one line on stderr
(once per process): what is compiled, that it happens once, about how long it takes. A first run never
sits silent; a warm run says nothing. ``ERRPLAN_COMPILE_NOTICE=0`` silences it.

How: numba's ``FunctionCache.load_overload`` is wrapped here (the one place errplan touches numba's
internals); a ``None`` result for a function of errplan is a compile about to start.

The lowest layer: numba and the standard library only.
"""
from __future__ import annotations

import os
import sys
from typing import Callable

import numba
from numba.core import caching

#: what a first run took to compile on the reference machine (2 cores), for the notice
COMPILE_ESTIMATE = "about 1 to 2 minutes on 2 cores for the planar and spatial kernels together"

_STATE = {"announced": False, "label": "errplan"}


def njit(*args, **options) -> Callable:
    """``numba.njit`` with ``cache=True`` unless given. Used as ``@njit``, ``@njit(...)`` or ``njit(f, ...)``."""
    options.setdefault("cache", True)
    if len(args) == 1 and callable(args[0]):
        return numba.njit(**options)(args[0])
    return numba.njit(**options)


def set_label(label: str) -> None:
    """How the notice names the run (the CLI sets ``errplan <command>``)."""
    _STATE["label"] = label


def announce(stream=None) -> bool:
    """Print the compile notice on ``stream`` (stderr) unless it was printed already or is silenced."""
    if _STATE["announced"] or os.environ.get("ERRPLAN_COMPILE_NOTICE", "1") == "0":
        return False
    _STATE["announced"] = True
    stream = stream or sys.stderr
    stream.write(f"{_STATE['label']}: compiling numerical kernels for this machine; this happens once, on the "
                 f"first run ({COMPILE_ESTIMATE}), later runs load them from the cache\n")
    stream.flush()
    return True


_load_overload = caching.FunctionCache.load_overload


def _load_overload_or_announce(self, sig, target_context):
    res = _load_overload(self, sig, target_context)
    if res is None and getattr(getattr(self, "_py_func", None), "__module__", "").startswith("errplan"):
        announce()
    return res


if getattr(caching.FunctionCache.load_overload, "__name__", "") != "_load_overload_or_announce":
    caching.FunctionCache.load_overload = _load_overload_or_announce
