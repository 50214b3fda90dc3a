"""The first run talks (issue 17): before errplan compiles its kernels it says so on stderr, once, in one
line; a warm cache says nothing. The kernels are numba's with an on-disk cache (errplan.jit)."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from errplan import jit

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"


def test_a_cold_cache_is_announced_in_one_line_before_the_compile(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"), ERRPLAN_COMPILE_NOTICE="1")
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "errplan", "fields", str(PORT), "--out", str(tmp_path / "f.npz"),
                          "--resolution", "0.02"], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                         env=env, cwd=tmp_path)
    try:
        line = p.stderr.readline()
        elapsed = time.perf_counter() - t0
    finally:
        p.kill()
        p.wait()
    assert line.startswith("errplan fields: compiling numerical kernels") and "once" in line and "minute" in line, line
    assert line.endswith("\n") and line.count("\n") == 1
    assert elapsed < 10.0, elapsed  # the first line of a first run comes within seconds
    assert not (tmp_path / "f.npz").exists()


@pytest.mark.slow
def test_a_warm_cache_says_nothing(tmp_path):
    """The same command again: the kernels load from the cache, and stderr stays empty."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"), ERRPLAN_COMPILE_NOTICE="1")
    argv = [sys.executable, "-m", "errplan", "fields", str(PORT), "--out", str(tmp_path / "f.npz"), "--resolution",
            "0.04", "--metrics", "G_norm", "--workers", "2"]
    first = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=900)
    assert first.returncode == 0, first.stderr
    assert first.stderr.count("compiling numerical kernels") == 1  # one line, not one per worker
    again = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert again.returncode == 0 and again.stderr == ""


def test_njit_is_numbas_with_a_disk_cache():
    @jit.njit
    def twice(x):
        return 2.0 * x

    @jit.njit(error_model="numpy")
    def half(x):
        return x / 2.0

    @jit.njit
    def both(x):
        return half(twice(x))  # a compiled caller of compiled callees, none with a C-callable wrapper

    assert twice(np.float64(3.0)) == 6.0 and half(1.0) == 0.5 and both(5.0) == 5.0
    assert type(twice._cache).__name__ == "FunctionCache" and half.targetoptions["error_model"] == "numpy"
    assert all(f.targetoptions["no_cfunc_wrapper"] for f in (twice, half, both))


def test_compiled_callers_call_a_wrapperless_twin_and_python_gets_its_own():
    """A kernel called only from compiled code is compiled once, without the Python wrapper (its twin,
    jit.Dispatcher._native); Python calling it compiles the wrapped version then, and both give the
    same numbers."""
    @jit.njit(cache=False)
    def inner(a, k):
        return a[k] * 2.0 + a.shape[0]

    @jit.njit(cache=False)
    def outer(a):
        s = 0.0
        for k in range(a.shape[0]):
            s += inner(a, k)
        return s

    a = np.arange(4.0)
    assert outer(a) == 2.0 * a.sum() + 16.0
    twin = inner._native()
    assert not inner.signatures  # Python never called it: no wrapped version was compiled
    assert twin.signatures and twin.targetoptions["no_cpython_wrapper"] and twin._native() is None
    assert twin.py_func.__code__ is inner.py_func.__code__ and twin.__name__ == "inner__native"
    assert inner(a, 3) == 10.0 and len(inner.signatures) == 1  # now it has its own
    assert outer(a + 1.0) == 2.0 * (a + 1.0).sum() + 16.0  # the caller still links the twin
    assert inner._native() is twin and len(twin.signatures) == 1


def _types_of(disp):
    """What numba inferred for a compiled kernel: the type of every variable and of every call."""
    ann = disp.overloads[disp.signatures[0]].type_annotation
    return (sorted((k, str(v)) for k, v in ann.typemap.items()),
            sorted((str(k), str(v)) for k, v in ann.calltypes.items()))


def test_remembered_call_types_are_the_ones_numba_finds():
    """jit._memoize_call_types keeps numba's answer to "how does this built-in or overloaded function
    type on these arguments". A kernel with arithmetic of mixed types, math, numpy constructors, builtins
    and tuples types the same with numba's own search (first) as with the remembered answers (twice,
    the second time all from the memo); a call no template accepts still fails as numba fails it."""
    import math

    import numba
    from numba.core import errors
    from numba.core.types import functions as fn

    memo = fn.BaseFunction.get_call_type
    assert memo._errplan_memo

    def kernel(x, n, flag):
        out = np.zeros((n, 3))
        idx = np.empty(n, np.int64)
        t = (1.0, 2, True)
        for i in range(n):
            v = math.sqrt(abs(x[i % x.shape[0]])) + i / 3 + (i // 2) * t[0] - t[1]
            out[i, 0] = min(v, 2.5) if flag else max(v, -1.0)
            out[i, 1] = math.atan2(v, 1.0 + i) ** 2
            out[i, 2] = np.float32(v) * 2
            idx[i] = int(v) % 7
        return out.sum() + idx.sum() + (n > 2) + np.isnan(x).sum()

    args = (np.linspace(-1.0, 1.0, 5), 6, True)
    found = []
    for method in (memo.__wrapped__, memo, memo):
        fn.BaseFunction.get_call_type = method
        try:
            d = numba.njit(cache=False)(kernel)  # a new dispatcher: typed afresh
            found.append((d(*args), _types_of(d)))
        finally:
            fn.BaseFunction.get_call_type = memo
    assert found[0] == found[1] == found[2]
    bad = numba.njit(cache=False)(lambda s: math.sqrt(s))
    with pytest.raises(errors.TypingError, match="sqrt"):
        bad("text")


def test_starting_errplan_skips_numbas_blas_import_and_keeps_blas_working():
    """errplan.jit defers numba's import-time BLAS check (which imports all of scipy.linalg, 0.3-0.4 s of
    every command's start). Loading numba's array math then imports no scipy.linalg, numba still
    believes BLAS is there, the real check is back for compiles, and a new kernel that needs BLAS
    compiles and runs."""
    code = (
        "import sys, errplan.jit, numba, numpy as np\n"
        "from numba.core.registry import cpu_target\n"
        "cpu_target.target_context.refresh()  # what a compile does first: loads numba's array maths\n"
        "import numba.np.arraymath as am, numba.np.linalg as nla\n"
        "assert 'scipy.linalg' not in sys.modules, 'scipy.linalg imported'\n"
        "assert am._HAVE_BLAS\n"
        "assert nla.ensure_blas.__name__ == 'ensure_blas' and am.ensure_blas is nla.ensure_blas\n"
        "f = numba.njit(lambda a, b: np.dot(a, b))\n"
        "a = np.arange(6.0).reshape(2, 3)\n"
        "assert np.array_equal(f(a, a.T), a @ a.T)\n"
        "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_a_warm_kernel_loads_without_numbas_registries_and_a_later_compile_still_works():
    """A cache hit of an errplan kernel initializes numba's runtime only, not its typing and lowering
    registries (about 0.4 s of every command's start). In a fresh process, after the planar arm's compiled
    forward kinematics ran from the cache: numba's array maths is not imported; a new kernel (an array
    allocated) still compiles and runs (numba refreshes fully first); and the loaded kernel
    gives the same wrists after that, within rounding of its numpy reference."""
    code = (
        "import sys, numpy as np\n"
        "from errplan.api import load_scenario\n"
        "from errplan.kinematics import arm_for\n"
        "arm = arm_for(load_scenario(sys.argv[1]).robot)\n"
        "q = np.array([[0.1, -0.4], [0.5, 0.2], [-1.0, 0.7]])\n"
        "a = arm.forward(q)\n"
        "if sys.argv[2] == 'warm': sys.exit(0)\n"
        "light = 'numba.np.arraymath' not in sys.modules\n"
        "import numba\n"
        "f = numba.njit(lambda x: np.ones(3) * x)\n"
        "assert np.array_equal(f(2.5), np.full(3, 2.5))\n"
        "assert np.array_equal(arm.forward(q), a)\n"
        "assert np.allclose(a, arm._forward_numpy(q), rtol=0, atol=1e-15)  # metres: a few ULP of 0.4 m\n"
        "print('light' if light else 'full')\n")
    run = [sys.executable, "-c", code, str(PORT)]
    subprocess.run([*run, "warm"], capture_output=True, text=True, timeout=600)  # a cold cache: compiled, stored
    out = subprocess.run([*run, "test"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip() == "light", (out.stdout, out.stderr[-2000:])


def test_a_kernel_is_recompiled_when_a_callee_in_another_file_changes(tmp_path):
    """numba keys a cached kernel on its own file only; errplan's also on the files of everything it
    calls and the constants they import (jit.closure_digest). Kernel f in a.py calls g in b.py and
    reads a constant imported from c.py: after b.py or c.py changes, f runs the new code (numba alone
    loads f's stale machine code, tried); unchanged, f loads from the cache."""
    pkg = tmp_path / "kpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from errplan.jit import njit\nfrom .b import g\nfrom .c import K\n\n\n"
                              "@njit(cache=True)\ndef f(x):\n    return g(x) + K\n")
    (pkg / "b.py").write_text("from errplan.jit import njit\n\n\n@njit(cache=True)\ndef g(x):\n    return 2.0 * x\n")
    (pkg / "c.py").write_text("K = 1.0\n")
    script = ("import sys; sys.path.insert(0, sys.argv[1])\n"
              "from errplan import jit; jit.CLOSURE_PACKAGES.add('kpkg')\n"
              "from kpkg.a import f\n"
              "print(f(1.0), f.stats.cache_hits.get(f.signatures[0], 0) if f.signatures else 0)\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"), ERRPLAN_COMPILE_NOTICE="0")

    def run():
        out = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True,
                             env=env, check=True).stdout.split()
        return float(out[0]), int(out[1])

    assert run() == (3.0, 0)
    assert run() == (3.0, 1)          # from the cache
    time.sleep(0.01)
    (pkg / "b.py").write_text("from errplan.jit import njit\n\n\n@njit(cache=True)\ndef g(x):\n    return 3.0 * x\n")
    assert run() == (4.0, 0)          # the callee changed: compiled again
    assert run() == (4.0, 1)
    (pkg / "c.py").write_text("K = 5.0\n")
    assert run() == (8.0, 0)          # the imported constant changed
    assert run() == (8.0, 1)
