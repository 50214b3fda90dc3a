"""What a path is worth on the fields: :class:`PathReport` (the ``P`` object of the plan JSON)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def jsonable(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass
class PathReport:
    """One path of a query (the ``P`` object of the plan JSON, docs/interfaces.md).

    Attributes
    ----------
    path : ndarray (n, d)
        Vertices ``[y, z]`` or ``[x, y, z]`` (m) from start to goal; straight segments between them.
    cost : float or None
        ``integral (1 + weight * metric) ds`` (m), exact on the multilinear field; None when the
        path leaves the robust workspace (the field is undefined there).
    length : float
        Length (m).
    max_G_norm, max_phi_hat_max : float or None
        Largest worst-case ``||G||`` (at the scenario gain) and ``phi_hat_max`` (rad) along the path:
        the exact maximum of the multilinear fields on every piece of every segment
        (:meth:`CostMap.field_max`); None outside the workspace or when the field was not computed.
    valid : bool
        The path stays in the usable region (workspace and, if asked, certifiable).
    in_workspace : bool
        The path stays in the robust workspace (reachable under every error instance).
    length_G_above_1 : float or None
        Length (m) of the path where the worst-case ``||G|| >= 1`` (no monotonic convergence
        guaranteed at the scenario gain).
    max_rho_star : float or None
        Largest ``rho_star`` along the path (when the fields have it).
    """

    path: np.ndarray
    cost: float | None
    length: float
    max_G_norm: float | None
    max_phi_hat_max: float | None
    valid: bool
    in_workspace: bool
    length_G_above_1: float | None = None
    max_rho_star: float | None = None

    def to_json(self) -> dict:
        return {"path": [[float(v) for v in p] for p in self.path], "cost": jsonable(self.cost),
                "length": float(self.length), "max_G_norm": jsonable(self.max_G_norm),
                "max_phi_hat_max": jsonable(self.max_phi_hat_max), "valid": bool(self.valid),
                "in_workspace": bool(self.in_workspace), "length_G_above_1": jsonable(self.length_G_above_1),
                "max_rho_star": jsonable(self.max_rho_star)}


def path_report(cm, path, workspace_map=None) -> PathReport:
    """The :class:`PathReport` of a polyline on ``cm`` (``workspace_map``: the same objective
    without the certifiable restriction, used for paths that leave the usable region)."""
    from .costmap import CostMap

    path = np.asarray(path, float).reshape(-1, cm.dim)
    length = float(np.sum(np.hypot.reduce(np.diff(path, axis=0), axis=1))) if len(path) > 1 else 0.0
    valid, cost = cm.path_cost(path)
    wm = workspace_map
    if valid:
        in_ws = True
    else:
        if wm is None:
            wm = cm if not cm.certifiable else CostMap(cm.mf, cm.metric, cm.weight, certifiable=False)
        in_ws, cost = wm.path_cost(path)
    mx_g = mx_p = above = mx_r = None
    if in_ws:
        m = cm if valid else wm
        if getattr(cm.mf, "G_norm", None) is not None:
            mx_g = m.field_max("G_norm", path)
            above = m.field_length_above("G_norm", path, 1.0)
        if getattr(cm.mf, "phi_hat_max", None) is not None:
            mx_p = m.field_max("phi_hat_max", path)
        if getattr(cm.mf, "rho_star", None) is not None:
            mx_r = m.field_max("rho_star", path)
    else:
        cost = None
    return PathReport(path, cost, length, mx_g, mx_p, bool(valid), bool(in_ws), above, mx_r)
