"""Input checks shared by every command, done before any work starts.

- :func:`read_text`: a text input file (scenario, measured-data CSV) read as UTF-8. A missing
  file, a directory, a device, an unreadable file, a binary file, UTF-16/UTF-32 text or any other
  byte sequence that is not UTF-8 gives one error line naming the file and the problem (never a
  ``UnicodeDecodeError`` traceback). A UTF-8 byte-order mark is accepted and dropped.
- :func:`check_allocation`: every size that follows from the input (grid points, error-set
  samples, CSV rows, simulation steps) is checked against what the machine can hold *before* the
  arrays are allocated: ``n_items * bytes_per_item`` against a budget, a fixed fraction
  (:data:`BUDGET_FRACTION`) of the memory available to this process, read once (``MemAvailable``
  of ``/proc/meminfo``, lowered to the cgroup's limit when the process runs in a container; a
  constant, :data:`FALLBACK_AVAILABLE`, when neither can be read). An absurd value is one error
  naming the key, the value and the memory it would need (``6.0 TiB``).

``ERRPLAN_MEMORY_BUDGET`` (bytes; suffixes K, M, G, T with binary units) overrides the budget, for
tests and for machines where the estimate is wrong.
"""
from __future__ import annotations

import math
import os
import stat
from pathlib import Path

from .errors import DataError, ErrplanError, ScenarioError

#: the share of the available memory one errplan process may plan to use
BUDGET_FRACTION = 0.5
#: assumed available memory (bytes) when it cannot be read from the system
FALLBACK_AVAILABLE = 4 * 2**30
#: bytes a text file costs in memory per byte on disk while it is read and decoded (bytes + str)
TEXT_BYTES_PER_BYTE = 3

_available: int | None = None
_UNITS = ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB", "ZiB", "YiB")


# ----------------------------------------------------------------------------- memory
def human_bytes(n: float) -> str:
    """``6.0 TiB``, ``512 B``, ``3.2 GiB`` (binary units); huge values in powers of ten of YiB."""
    n = float(n)
    if not math.isfinite(n):
        return "an unbounded amount of memory"
    i = 0
    while n >= 1024 and i < len(_UNITS) - 1:
        n /= 1024
        i += 1
    if i == 0:
        return f"{int(n)} B"
    return f"{n:.1f} {_UNITS[i]}" if n < 1e4 else f"{n:.3g} {_UNITS[i]}"


def _read_int(path: str) -> int | None:
    try:
        with open(path) as f:
            text = f.read().strip()
    except OSError:
        return None
    try:
        return int(text)
    except ValueError:
        return None  # "max" (no limit) or garbage


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _cgroup_available() -> int | None:
    """Memory left under this process's cgroup limit (v2, then v1), or None without a limit."""
    for lim_path, use_path in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                               ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        lim = _read_int(lim_path)
        if lim is None or lim >= 2**60:  # no limit ("max", or v1's huge sentinel)
            continue
        used = _read_int(use_path) or 0
        return max(lim - used, 0)
    return None


def available_memory() -> int:
    """Memory (bytes) available to this process, read once per process (see the module docstring)."""
    global _available
    if _available is None:
        vals = [v for v in (_meminfo_available(), _cgroup_available()) if v is not None and v > 0]
        if not vals and hasattr(os, "sysconf"):
            try:
                vals = [os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")]
            except (OSError, ValueError):
                vals = []
        _available = int(min(vals)) if vals else FALLBACK_AVAILABLE
    return _available


def _parse_bytes(text: str) -> int | None:
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    mult = 1
    for i, s in enumerate("KMGT", start=1):
        if t.endswith(s):
            t, mult = t[:-1], 1024 ** i
            break
    try:
        v = float(t) * mult
    except ValueError:
        return None
    return int(v) if math.isfinite(v) and v > 0 else None


def memory_budget() -> int:
    """Bytes one errplan process plans to use at most: ``ERRPLAN_MEMORY_BUDGET`` if set, else
    :data:`BUDGET_FRACTION` of :func:`available_memory`."""
    env = os.environ.get("ERRPLAN_MEMORY_BUDGET")
    if env:
        v = _parse_bytes(env)
        if v is None:
            raise ErrplanError(f"ERRPLAN_MEMORY_BUDGET = {env!r}: expected a number of bytes > 0 (suffix K, M, G or T allowed)")
        return v
    return int(BUDGET_FRACTION * available_memory())


def _show(value) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (Path, str)):
        return str(value)
    return repr(value)


def check_allocation(key: str, value, n_items, bytes_per_item: int, what: str = "array") -> None:
    """Raise :class:`ErrplanError` when ``n_items * bytes_per_item`` exceeds :func:`memory_budget`.

    ``key`` and ``value`` name the input the size follows from (``[instrument] length``, ``1e9``);
    ``what`` says what would be allocated (``"the bench's start grid"``). ``n_items`` may be a
    float (a size computed before it can overflow an integer); a size that is not finite (NaN, inf)
    or negative is refused too.
    """
    try:
        n = float(n_items)
    except (TypeError, ValueError, OverflowError):
        n = float("nan")
    if isinstance(n_items, int) and not isinstance(n_items, bool):
        n = float(n_items) if n_items < 2**1000 else float("inf")
    if not math.isfinite(n) or n < 0:
        raise ErrplanError(f"{key} = {_show(value)}: {what} would need {n_items!r} items, not a finite size "
                           f"(the value is absurd for this input)")
    need = n * float(bytes_per_item)
    budget = memory_budget()
    if need > budget:
        avail = available_memory()
        count = f"{n:.3g}" if n >= 1e6 else f"{int(n):,}"
        raise ErrplanError(f"{key} = {_show(value)}: {what} would need {human_bytes(need)} ({count} x {bytes_per_item} B), "
                           f"more than the {human_bytes(budget)} errplan may use here "
                           f"({int(100 * BUDGET_FRACTION)}% of {human_bytes(avail)} available)")


# ----------------------------------------------------------------------------- text files
def _error_class(what: str) -> type[ErrplanError]:
    w = what.lower()
    if "scenario" in w:
        return ScenarioError
    if "data" in w or "csv" in w:
        return DataError
    return ErrplanError


def _utf16_like(raw: bytes) -> str | None:
    """'UTF-16' / 'UTF-32' when the bytes look like such text without a byte-order mark: mostly
    ASCII characters, so the high bytes of the code units are zero and the low bytes are not."""
    h = raw[:4096]
    n4, n2 = len(h) // 4, len(h) // 2
    if n4 >= 2:
        cols = [h[o::4][:n4] for o in range(4)]
        for low, high in ((0, (1, 2, 3)), (3, (0, 1, 2))):  # little / big endian
            if all(cols[o].count(0) > 0.9 * n4 for o in high) and n4 - cols[low].count(0) > 0.8 * n4:
                return "UTF-32"
    if n2 >= 2:
        even, odd = h[0::2][:n2], h[1::2][:n2]
        for low, high in ((even, odd), (odd, even)):
            if high.count(0) > 0.8 * n2 and n2 - low.count(0) > 0.8 * n2:
                return "UTF-16"
    return None


def decode_text(raw: bytes, name: str, what: str = "scenario file") -> str:
    """Decode file contents as UTF-8 (an optional UTF-8 byte-order mark is dropped); anything
    else raises one error naming the file and the problem."""
    cls = _error_class(what)
    for bom, enc in ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"),
                     (b"\xff\xfe", "UTF-16"), (b"\xfe\xff", "UTF-16")):
        if raw.startswith(bom):
            raise cls(f"{name}: the {what} is {enc} text; errplan reads UTF-8 (save it as UTF-8)")
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    if b"\x00" in raw:
        enc = _utf16_like(raw)
        if enc:
            raise cls(f"{name}: the {what} looks like {enc} text without a byte-order mark; errplan reads UTF-8 "
                      f"(save it as UTF-8)")
        raise cls(f"{name}: the {what} is a binary file (it contains NUL bytes), not UTF-8 text")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        bad = raw[e.start:e.start + 1].hex()
        raise cls(f"{name}: the {what} is not UTF-8 text (byte 0x{bad} at offset {e.start}, line {line}); "
                  f"save it as UTF-8") from None


def read_text(path, what: str = "scenario file") -> str:
    """Read a text file as UTF-8; missing file, directory, unreadable, too large for memory, or not
    UTF-8 (binary, UTF-16 ...) -> :class:`ScenarioError` / :class:`DataError` / :class:`ErrplanError`
    (by ``what``) with one line naming the file and the problem."""
    return decode_text(read_bytes(path, what), str(path), what)


def read_bytes(path, what: str = "scenario file", cls: type[ErrplanError] | None = None) -> bytes:
    """The bytes of a regular file, or one error (``cls``, default by ``what``) naming the file and the
    problem: missing, a directory, a device, unreadable, too large for this machine's memory."""
    cls = cls or _error_class(what)
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise cls(f"{p}: {what} not found") from None
    except NotADirectoryError:
        raise cls(f"{p}: {what} not found (a parent of it is not a directory)") from None
    except PermissionError:
        raise cls(f"{p}: cannot read the {what}: permission denied") from None
    except (OSError, ValueError) as e:
        raise cls(f"{p}: cannot read the {what}: {getattr(e, 'strerror', None) or e}") from None
    if stat.S_ISDIR(st.st_mode):
        raise cls(f"{p}: cannot read the {what}: it is a directory")
    if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) or stat.S_ISSOCK(st.st_mode):
        raise cls(f"{p}: cannot read the {what}: it is a device or socket, not a regular file")
    budget = memory_budget()
    limit = max(budget // TEXT_BYTES_PER_BYTE, 1)
    if stat.S_ISREG(st.st_mode):
        check_allocation(str(p), f"{st.st_size} bytes", st.st_size, TEXT_BYTES_PER_BYTE, f"reading the {what}")
    try:
        with open(p, "rb") as f:
            raw = f.read(limit + 1)  # a pipe has no size: read at most the budget
    except PermissionError:
        raise cls(f"{p}: cannot read the {what}: permission denied") from None
    except IsADirectoryError:
        raise cls(f"{p}: cannot read the {what}: it is a directory") from None
    except OSError as e:
        raise cls(f"{p}: cannot read the {what}: {e.strerror or e}") from None
    if len(raw) > limit:
        check_allocation(str(p), "a stream longer than the budget", len(raw), TEXT_BYTES_PER_BYTE, f"reading the {what}")
    return raw


def check_output(option: str, value) -> Path | None:
    """An output path given on the command line: its directory must exist and it must not be a
    directory itself. Returns the path (None when the option is not given)."""
    if value is None or value == "":
        return None
    p = Path(value)
    if p.is_dir():
        raise ErrplanError(f"{option} {value}: is a directory, expected a file name")
    parent = p.parent
    if not parent.exists():
        raise ErrplanError(f"{option} {value}: directory {p.parent} does not exist")
    if not parent.is_dir():
        raise ErrplanError(f"{option} {value}: {p.parent} is not a directory")
    return p
