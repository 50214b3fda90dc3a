"""Colours, colour maps and names shared by the views: the tip-plane convention (:func:`uv`), entity names
for queries, the field ranges and maps, Turbo and Viridis. numpy only."""
from __future__ import annotations

import math
import re

import numpy as np

FIELD_RANGES = {"G_norm": (0.0, 1.2), "phi_hat_max": (0.0, math.pi / 2), "rho_star": (0.0, 1.0)}
FIELD_COLORMAPS = {"G_norm": "Turbo", "phi_hat_max": "Viridis", "rho_star": "Plasma"}
PLANNED_COLOR = (40, 220, 90)
DIRECT_COLOR = (240, 60, 60)
PORT_TRUE_COLOR = (255, 255, 255)
PORT_EST_COLOR = (255, 200, 0)


#: ports closer than this share of the scene's size get one label: apart, the two labels overprint
PORT_LABEL_SHARE = 0.15


def port_labels(true, estimate, extent: float, true_text: str = "true port") -> tuple[list | None, list | None]:
    """The labels of the true (white) and the estimated (yellow) port: each its own where they lie apart;
    where they are closer than ``PORT_LABEL_SHARE`` of the scene's ``extent`` (m), where the viewer would
    draw the two labels over each other, one label on the true port naming both and their distance (and
    none on the estimate)."""
    d = float(np.linalg.norm(np.subtract(estimate, true)))
    if d >= PORT_LABEL_SHARE * float(extent):
        return [true_text], ["estimated port"]
    if d == 0.0:
        return [f"{true_text} = estimated port"], None
    return [f"{true_text} (white), estimated port (yellow) {d * 1000:.1f} mm away"], None


def uv(pts) -> np.ndarray:
    """Tip-plane points ``[y, z]`` (..., 2) -> viewer 2-D coordinates ``(z, -y)``."""
    p = np.asarray(pts, float)
    return np.stack([p[..., 1], -p[..., 0]], axis=-1)


def entity_name(name: str) -> str:
    """A query name as one entity-path part (letters, digits, ``-``, ``_``)."""
    s = re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_")
    return s or "query"


def entity_names(runs) -> list[str]:
    """One distinct entity-path part per query (``_2``, ``_3``... appended on collisions)."""
    out, seen = [], set()
    for r in runs:
        base = entity_name(r.name)
        q, i = base, 1
        while q in seen:
            i += 1
            q = f"{base}_{i}"
        seen.add(q)
        out.append(q)
    return out


TURBO_R = (0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943)
TURBO_G = (0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604)
TURBO_B = (0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973)
SURFACE_COLORS = {"G_norm_1": (255, 60, 40, 90), "rho_star_margin": (80, 140, 255, 90)}
SLICE_ALPHA = 110


def turbo(t) -> np.ndarray:
    """Turbo colormap for ``t`` in [0, 1] (a degree-5 polynomial fit per channel, within ~30/255 of
    the published table): RGB uint8 (..., 3)."""
    t = np.clip(np.asarray(t, float), 0.0, 1.0)
    out = [sum(c * t ** i for i, c in enumerate(coef)) for coef in (TURBO_R, TURBO_G, TURBO_B)]
    return (np.clip(np.stack(out, axis=-1), 0.0, 1.0) * 255).astype(np.uint8)


BEST_COLOR = (255, 60, 200)
REFINED_COLOR = (255, 255, 255)
CERTIFIED_COLOR = (40, 220, 90)
NOT_CERTIFIED_COLOR = (240, 60, 60)
UNREACHABLE_COLOR = (110, 110, 110)
REGION_COLOR = (255, 200, 0)
#: viridis anchors (0, 0.25, 0.5, 0.75, 1) for the 3-D cubes (the 2-D heat maps use rerun's colormap)
_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float)


def viridis(v) -> np.ndarray:
    """RGB (n, 3) uint8 of values in [0, 1] (NaN: grey)."""
    v = np.asarray(v, float)
    t = np.clip(np.nan_to_num(v, nan=0.0), 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i = np.minimum(np.floor(t).astype(int), len(_VIRIDIS) - 2)
    f = (t - i)[..., None]
    rgb = (1 - f) * _VIRIDIS[i] + f * _VIRIDIS[i + 1]
    rgb[~np.isfinite(v)] = 110
    return rgb.astype(np.uint8)
