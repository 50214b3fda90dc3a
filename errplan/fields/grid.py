"""Metric fields on a regular grid of tips: :class:`MetricField` (npz i/o, interpolation, summary)
and the grid's construction."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ErrplanError


# ----------------------------------------------------------------------------- field object
METRIC_NAMES = ("G_norm", "phi_hat_max", "phi_max", "rho_star", "k_star")


@dataclass
class MetricField:
    """Worst-case metric arrays on a regular grid of tips; NaN outside the workspace.

    Planar: axes ``y, z`` and arrays (ny, nz). Spatial: axes ``x, y, z`` and arrays (nx, ny, nz)
    (``x`` is None in the plane). A metric not computed (``--metrics``) is None.
    """

    y: np.ndarray
    z: np.ndarray
    valid: np.ndarray
    G_norm: np.ndarray | None
    phi_hat_max: np.ndarray | None
    phi_max: np.ndarray | None
    rho_star: np.ndarray | None = None
    k_star: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    x: np.ndarray | None = None
    clearance: np.ndarray | None = None  # m: robust shaft clearance to [anatomy] (spatial, with obstacles)

    @property
    def dim(self) -> int:
        return 2 if self.x is None else 3

    @property
    def axis_names(self) -> tuple[str, ...]:
        return ("y", "z") if self.x is None else ("x", "y", "z")

    @property
    def axes(self) -> tuple[np.ndarray, ...]:
        return tuple(getattr(self, a) for a in self.axis_names)

    @property
    def resolution(self) -> float:
        if "resolution" in self.meta:
            return float(self.meta["resolution"])
        return float(self.y[1] - self.y[0])

    def array(self, name: str) -> np.ndarray:
        a = getattr(self, name, None)
        if a is None:
            raise ErrplanError(f"field {name!r} was not computed (use --rho-star, --metrics or "
                               "compute_fields(rho_star=True))")
        return a

    def points(self) -> np.ndarray:
        """Tip positions (*shape, d) of the grid."""
        return np.stack(np.meshgrid(*self.axes, indexing="ij"), axis=-1)

    def sample(self, name: str, pts: np.ndarray) -> np.ndarray:
        """Multilinear (bi- or trilinear) interpolation of a field at points (..., d); NaN where a
        corner is invalid or the point is off the grid."""
        a = self.array(name)
        pts = np.asarray(pts, float)
        axes = self.axes
        i0s, ts = [], []
        inside = np.ones(pts.shape[:-1], bool)
        for k, ax in enumerate(axes):
            f = (pts[..., k] - ax[0]) / self.resolution
            i0 = np.floor(f).astype(int)
            inside &= (i0 >= 0) & (i0 < len(ax) - 1)
            i0 = np.clip(i0, 0, len(ax) - 2)
            i0s.append(i0)
            ts.append(f - i0)
        v = np.zeros(pts.shape[:-1])
        for corner in np.ndindex(*(2,) * len(axes)):
            wgt = np.ones(pts.shape[:-1])
            for k, c in enumerate(corner):
                wgt = wgt * (ts[k] if c else 1 - ts[k])
            v = v + wgt * a[tuple(i0 + c for i0, c in zip(i0s, corner))]
        return np.where(inside, v, np.nan)

    def summary(self) -> dict:
        """Share of the workspace with ||G|| < 1 (and rho* < 1) and max/median/min of each field."""
        n = int(self.valid.sum())
        out: dict = {"grid": [len(a) for a in self.axes], "resolution": self.resolution, "valid_points": n}
        if self.dim == 2:
            out["workspace_area_m2"] = n * self.resolution**2
        else:
            out["workspace_volume_m3"] = n * self.resolution**3
        if n == 0:
            return out
        if self.G_norm is not None:
            out["share_G_below_1"] = float(np.mean(self.G_norm[self.valid] < 1.0))
        if self.clearance is not None:
            c = self.clearance[np.isfinite(self.clearance)]
            out["blocked_points"] = int(self.meta.get("anatomy", {}).get("blocked_points", 0))
            if len(c):
                out["clearance"] = {"max": float(c.max()), "median": float(np.median(c)), "min": float(c.min())}
        if self.rho_star is not None:
            out["share_rho_star_below_1"] = float(np.mean(self.rho_star[self.valid] < 1.0))
        for name in METRIC_NAMES:
            a = getattr(self, name)
            if a is not None:
                v = a[self.valid]
                out[name] = {"max": float(v.max()), "median": float(np.median(v)), "min": float(v.min())}
        return out

    # ---------------------------------------------------------------- io
    def save(self, path: str | Path) -> None:
        """Write the npz of docs/interfaces.md (atomically: nothing half-written)."""
        path = Path(path)
        arrays = {a: ax for a, ax in zip(self.axis_names, self.axes)}
        arrays["valid"] = self.valid
        for name in METRIC_NAMES:
            if getattr(self, name) is not None:
                arrays[name] = getattr(self, name)
        if self.clearance is not None:
            arrays["clearance"] = self.clearance
        arrays["meta"] = np.array(json.dumps(self.meta))
        tmp = path.with_name(path.name + ".part")
        try:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)  # uncompressed: 30x faster to write, 10 % larger
            tmp.replace(path)
        finally:
            tmp.unlink(missing_ok=True)

    @classmethod
    def load(cls, path: str | Path) -> "MetricField":
        with np.load(path) as d:
            meta = json.loads(str(d["meta"])) if "meta" in d else {}
            get = {n: (d[n] if n in d else None) for n in METRIC_NAMES}
            return cls(d["y"], d["z"], d["valid"].astype(bool), meta=meta, x=d["x"] if "x" in d else None,
                       clearance=d["clearance"] if "clearance" in d else None, **get)
