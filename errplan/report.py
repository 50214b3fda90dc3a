"""Output helpers shared by the commands: readable tables, atomic JSON, progress lines."""
from __future__ import annotations

import contextlib
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Iterable, Sequence

from .errors import ErrplanError


def format_table(headers: Sequence[str], rows: Iterable[Sequence[Any]], title: str | None = None) -> str:
    """A plain-text table with right-aligned numbers."""

    def cell(v: Any) -> str:
        if isinstance(v, bool):
            return "yes" if v else "no"
        if isinstance(v, float):
            if not math.isfinite(v):
                return "-"
            return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.3e}"
        return str(v)

    body = [[cell(v) for v in r] for r in rows]
    widths = [max([len(h)] + [len(r[i]) for r in body]) for i, h in enumerate(headers)]
    lines = []
    if title:
        lines.append(title)
    lines.append("  ".join(h.ljust(w) for h, w in zip(headers, widths)))
    lines.append("  ".join("-" * w for w in widths))
    for r in body:
        lines.append("  ".join(c.rjust(w) if _numeric(c) else c.ljust(w) for c, w in zip(r, widths)))
    return "\n".join(lines)


def _numeric(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


_STATUS_TEXT = {"left_workspace": "left the workspace", "max_steps": "did not converge within the step limit"}


def clearance_text(kind: str, clearance: float, status: str, steps: int, corners: Sequence[tuple[float | None, str]] = ()) -> str:
    """One path's shaft clearance for the summary, with the run's status beside it when the run did not
    converge: a clearance measured over a run that stopped early (it left the workspace after one step)
    is no evidence of a safe path. ``corners``: (clearance or None, status) of every corner replay."""
    text = f"{kind} {clearance * 1000:.1f} mm"
    if status != "converged":
        text += f" over the {steps} step{'s' if steps != 1 else ''} it ran: {_STATUS_TEXT.get(status, status).upper()}"
    cs = [c for c, _ in corners if c is not None]
    if cs:
        text += f" (corners >= {min(cs) * 1000:.1f} mm"
        failed = {}
        for _, st in corners:
            if st != "converged":
                failed[st] = failed.get(st, 0) + 1
        for st, n in failed.items():
            text += f"; {n} of {len(corners)} corners {_STATUS_TEXT.get(st, st)}"
        text += ")"
    return text


NON_FINITE_KEY = "non_finite"
"""The key under which a JSON object says which of its values were not finite numbers (written as null)."""


def _kind(v: float) -> str:
    if math.isnan(v):
        return "nan"
    return "inf" if v > 0 else "-inf"


def _clean(obj: Any, path: str = "") -> tuple[Any, dict[str, str]]:
    """Convert numpy values to JSON types. A non-finite number is data, not a failure: it is written
    as ``null`` and the nearest enclosing object gets ``"non_finite": {"<key>[<index>]...": "inf" |
    "-inf" | "nan"}`` naming it (``inf`` an unbounded value, e.g. ||G|| where the controller's Jacobian
    is singular; ``nan`` an undefined one). Returns the value and the notes not yet attached."""
    try:
        import numpy as np
    except ImportError:  # pragma: no cover
        np = None
    if isinstance(obj, dict):
        out: dict[str, Any] = {}
        notes: dict[str, str] = {}
        for k, v in obj.items():
            cv, sub = _clean(v, f"{path}.{k}")
            out[str(k)] = cv
            notes.update({f"{k}{r}": kind for r, kind in sub.items()})
        if notes:
            if NON_FINITE_KEY in out:
                raise ErrplanError(f"internal: {path or 'top'} has its own key {NON_FINITE_KEY!r} in the JSON output")
            out[NON_FINITE_KEY] = notes
        return out, {}
    if isinstance(obj, (list, tuple)):
        items, notes = [], {}
        for i, v in enumerate(obj):
            cv, sub = _clean(v, f"{path}[{i}]")
            items.append(cv)
            notes.update({f"[{i}]{r}": kind for r, kind in sub.items()})
        return items, notes
    if np is not None and isinstance(obj, np.ndarray):
        return _clean(obj.tolist(), path)
    if np is not None and isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None, {"": _kind(obj)}
    return obj, {}


def to_json(obj: Any) -> str:
    """``obj`` as indented JSON; non-finite numbers become ``null``, named under ``non_finite``."""
    out, notes = _clean(obj)
    if notes:  # only a bare list at the top has nowhere to say it
        raise ErrplanError(f"internal: non-finite values at {sorted(notes)} of a JSON list")
    return json.dumps(out, indent=2, allow_nan=False)


def write_atomic(path: str | Path, text: str) -> None:
    """Write a text file atomically (temp file + rename): never half-written."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_json(path: str | Path, obj: Any) -> None:
    write_atomic(path, to_json(obj) + "\n")


class Progress:
    """Progress on stderr: an updating line on a terminal, a few lines otherwise."""

    def __init__(self, label: str, stream=None, quiet: bool = False):
        self.label = label
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.t0 = time.perf_counter()
        self._last_pct = -100

    def __call__(self, fraction: float, message: str = "") -> None:
        if self.quiet:
            return
        pct = int(100 * min(max(fraction, 0.0), 1.0))
        if self.tty:
            self.stream.write(f"\r{self.label}: {pct:3d}% {message:<40s}")
            self.stream.flush()
        elif pct >= self._last_pct + 25 or pct == 100 and self._last_pct != 100:
            self._last_pct = pct
            self.stream.write(f"{self.label}: {pct:3d}% {message} ({time.perf_counter() - self.t0:.1f} s)\n")

    @contextlib.contextmanager
    def cleared_on_error(self):
        """Run the block; on an :class:`ErrplanError` clear the progress line first, so that the error is
        the one line on stderr."""
        try:
            yield self
        except ErrplanError:
            if not self.quiet:
                self.stream.write("\r" + " " * 60 + "\r")
                self.stream.flush()
            raise

    def done(self) -> None:
        if not self.quiet and self.tty:
            self.stream.write(f"\r{self.label}: done in {time.perf_counter() - self.t0:.1f} s{' ' * 40}\n")
