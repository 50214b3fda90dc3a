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
