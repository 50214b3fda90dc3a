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


def test_starting_errplan_skips_numbas_blas_import_and_keeps_blas_working():
    """errplan.jit defers numba's import-time BLAS check (which imports all of scipy.linalg, 0.3-0.4 s of
    every command's start). Loading numba's array math then imports no scipy.linalg, numba still
    believes BLAS is there, the real check is back for compiles, and a new kernel that needs BLAS
    compiles and runs."""
    code = (
        "import sys, errplan.jit, numba, numpy as np\n"
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
