"""The answer of one tolerance query: :class:`ToleranceResult` (its JSON entry and its table row)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

Progress = Callable[[float, str], None]


@dataclass
class ToleranceResult:
    """One answered query. ``data`` holds the kind's keys of docs/interfaces.md ("tolerance JSON")
    plus the plot-ready ``curve`` and details; :meth:`to_dict` is the JSON entry."""

    name: str
    kind: str
    data: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """The JSON entry: every key of ``data`` but the private ones (``_arrays``: numpy arrays for
        the recording)."""
        out = {"name": self.name, "kind": self.kind}
        out.update(_jsonable({k: v for k, v in self.data.items() if not str(k).startswith("_")}))
        out["seconds"] = round(self.seconds, 3)
        return out

    def summary_row(self) -> list[Any]:
        """``[name, kind, answer, where, note]`` for the command's table."""
        d = self.data
        if self.kind == "port":
            return [self.name, f"port ({d['direction']})", f"{1000 * d['value']:.3f} mm",
                    _point(d["binding_point"]), d["binding"]]
        if self.kind == "tip_load":
            return [self.name, "tip_load", f"{d['value']:.4g} 1/m^2", _point(d["binding_point"]), d["binding"]]
        if self.kind == "port_placement":
            rho = d["max_rho_star"]
            note = f"max rho* {rho:.4f}" if isinstance(rho, float) and math.isfinite(rho) else "max rho* -"
            if "refined" in d:
                r = d["refined"]
                note += f"; refined {_point(r['port'])}: {100 * r['coverage']:.1f}%"
            return [self.name, "port_placement", f"coverage {100 * d['coverage']:.1f}%", f"best {_point(d['best'])}",
                    note]
        if self.kind in ("triad_placement", "setup_placement"):
            b = d["best"]
            bases = ("; bases " + "; ".join(f"{k} {_point(v['position'])}" for k, v in b["bases"].items())
                     if "bases" in b else "")
            return [self.name, self.kind, f"score {b['score']:.4f}",
                    "; ".join(f"{k} {_point(v)}" for k, v in b["ports"].items()) + bases,
                    f"both covered {100 * b['coverage']['both']:.1f}%, pruned {100 * d['search']['pruned_share']:.1f}%"]
        if self.kind == "insertion_band":
            band = d["band"]
            b = "none" if band is None else f"{band[0]:.3f} < r/L < {band[1]:.3f}"
            lb = " (3-D: lower bound, band at most)" if d.get("lower_bound") else ""
            return [self.name, "insertion_band", b, f"best r/L {d['best']:.3f}",
                    f"min worst ||G|| {d['best_G_norm']:.3f}{lb}"]
        if self.kind == "tracker_noise":
            lb = " (3-D: lower bound, noise at most)" if d.get("lower_bound") else ""
            return [self.name, "tracker_noise", f"{1000 * d['value']:.4f} mm, {d['angle_value']:.5f} rad",
                    f"r/L {d['binding_r_over_L']:.3f}", f"= {d['value'] / d['length']:.5f} L{lb}"]
        return [self.name, self.kind, "", "", ""]  # pragma: no cover


def _point(p) -> str:
    return "[" + ", ".join(f"{float(v):.4f}" for v in p) + "]"


def _jsonable(obj: Any) -> Any:
    """numpy -> JSON types; non-finite floats become ``None`` (JSON null: 'divergent/undefined')."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj

