"""One BLAS thread while calibrating and designing.

Calibration and experiment design run many small dense problems (local polynomial fits of a few
hundred rows, SVDs of 16-column Jacobians, batches of 16 x 16 inverses). With numpy's threaded
OpenBLAS on a 2-core machine that other processes keep busy, LAPACK's blocked routines on such
matrices spend their time waiting for threads: ``np.linalg.lstsq`` of a 400 x 80 matrix took 0.8 s
instead of 2 ms here. :func:`single_threaded_blas` sets numpy's OpenBLAS to one thread for the
duration (what ``threadpoolctl`` does, for the one library numpy ships) and restores it; where the
library or its entry points cannot be found it does nothing.
"""
from __future__ import annotations

import contextlib
import ctypes
import glob
import os

_LIB: object = False  # not looked up yet


def _openblas():
    """``(get, set)`` of numpy's bundled OpenBLAS thread count, or None."""
    global _LIB
    if _LIB is not False:
        return _LIB
    _LIB = None
    try:
        import numpy

        root = os.path.dirname(os.path.dirname(numpy.__file__))
        paths = sorted(glob.glob(os.path.join(root, "numpy.libs", "*openblas*")))
        for path in paths:
            lib = ctypes.CDLL(path)
            for get, set_ in (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                              ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
                              ("openblas_get_num_threads", "openblas_set_num_threads")):
                if hasattr(lib, get) and hasattr(lib, set_):
                    g, s = getattr(lib, get), getattr(lib, set_)
                    g.restype = ctypes.c_int
                    s.argtypes = [ctypes.c_int]
                    _LIB = (g, s)
                    return _LIB
    except (OSError, ImportError, AttributeError):  # pragma: no cover - another BLAS: leave it alone
        _LIB = None
    return _LIB


@contextlib.contextmanager
def single_threaded_blas():
    """Run the block with numpy's OpenBLAS on one thread (restored afterwards)."""
    lib = _openblas()
    if lib is None:
        yield
        return
    get, set_ = lib
    old = int(get())
    set_(1)
    try:
        yield
    finally:
        set_(max(old, 1))
