"""Metric fields on a regular grid of tips: :class:`MetricField` (npz i/o, interpolation, summary)
and the grid's construction."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ErrplanError
from ..kinematics.shaft import flexed_tip


# ----------------------------------------------------------------------------- field object
@dataclass
class MetricField:
    """Worst-case metric arrays on a regular ``(y, z)`` grid; NaN outside the workspace."""

    y: np.ndarray
    z: np.ndarray
    valid: np.ndarray
    G_norm: np.ndarray
    phi_hat_max: np.ndarray
    phi_max: np.ndarray
    rho_star: np.ndarray | None = None
    k_star: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    @property
    def resolution(self) -> float:
        if "resolution" in self.meta:
            return float(self.meta["resolution"])
        return float(self.y[1] - self.y[0])

    def array(self, name: str) -> np.ndarray:
        a = getattr(self, name, None)
        if a is None:
            raise ErrplanError(f"field {name!r} was not computed (use --rho-star or compute_fields(rho_star=True))")
        return a

    def points(self) -> np.ndarray:
        """Tip positions (ny, nz, 2) of the grid."""
        return np.stack(np.meshgrid(self.y, self.z, indexing="ij"), axis=-1)

    def sample(self, name: str, pts: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of a field at points (..., 2); NaN where a corner is invalid."""
        a = self.array(name)
        pts = np.asarray(pts, float)
        fy = (pts[..., 0] - self.y[0]) / self.resolution
        fz = (pts[..., 1] - self.z[0]) / self.resolution
        i0 = np.floor(fy).astype(int)
        j0 = np.floor(fz).astype(int)
        inside = (i0 >= 0) & (j0 >= 0) & (i0 < len(self.y) - 1) & (j0 < len(self.z) - 1)
        i0c = np.clip(i0, 0, len(self.y) - 2)
        j0c = np.clip(j0, 0, len(self.z) - 2)
        ty, tz = fy - i0c, fz - j0c
        v = ((1 - ty) * (1 - tz) * a[i0c, j0c] + ty * (1 - tz) * a[i0c + 1, j0c]
             + (1 - ty) * tz * a[i0c, j0c + 1] + ty * tz * a[i0c + 1, j0c + 1])
        return np.where(inside, v, np.nan)

    def summary(self) -> dict:
        """Share of the workspace with ||G|| < 1 (and rho* < 1) and max/median of each field."""
        n = int(self.valid.sum())
        out: dict = {"grid": [len(self.y), len(self.z)], "resolution": self.resolution, "valid_points": n,
                     "workspace_area_m2": n * self.resolution**2}
        if n == 0:
            return out
        out["share_G_below_1"] = float(np.mean(self.G_norm[self.valid] < 1.0))
        if self.rho_star is not None:
            out["share_rho_star_below_1"] = float(np.mean(self.rho_star[self.valid] < 1.0))
        for name in ("G_norm", "phi_hat_max", "phi_max", "rho_star", "k_star"):
            a = getattr(self, name)
            if a is not None:
                v = a[self.valid]
                out[name] = {"max": float(v.max()), "median": float(np.median(v)), "min": float(v.min())}
        return out

    # ---------------------------------------------------------------- io
    def save(self, path: str | Path) -> None:
        """Write the npz of docs/interfaces.md (atomically: nothing half-written)."""
        path = Path(path)
        arrays = {"y": self.y, "z": self.z, "valid": self.valid, "G_norm": self.G_norm,
                  "phi_hat_max": self.phi_hat_max, "phi_max": self.phi_max,
                  "meta": np.array(json.dumps(self.meta))}
        if self.rho_star is not None:
            arrays["rho_star"] = self.rho_star
            arrays["k_star"] = self.k_star
        tmp = path.with_name(path.name + ".part")
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> "MetricField":
        with np.load(path) as d:
            meta = json.loads(str(d["meta"])) if "meta" in d else {}
            return cls(d["y"], d["z"], d["valid"].astype(bool), d["G_norm"], d["phi_hat_max"], d["phi_max"],
                       d["rho_star"] if "rho_star" in d else None, d["k_star"] if "k_star" in d else None, meta)


# ----------------------------------------------------------------------------- computation
def _aligned_axis(lo: float, hi: float, res: float) -> np.ndarray:
    i0, i1 = math.floor(lo / res), math.ceil(hi / res)
    return np.arange(i0, i1 + 1) * res


def workspace_bounds(ev: "Evaluator") -> tuple[float, float, float, float]:
    """Bounding box (y0, y1, z0, z1) of tips reachable under any corner instance."""
    w = ev.arm.sample_wrists(161)
    tips = []
    for th in ev.errors.corners():
        port = ev.errors.port(th)
        r = np.linalg.norm(port - w, axis=-1)
        ww = w[(r < ev.length) & (r > 1e-6)]
        if len(ww):
            tips.append(flexed_tip(ww, port, ev.length, th[2]))
    if not tips:
        raise ErrplanError("the tip workspace is empty: no reachable wrist puts the shaft through the port")
    t = np.concatenate(tips)
    return float(t[:, 0].min()), float(t[:, 0].max()), float(t[:, 1].min()), float(t[:, 1].max())


