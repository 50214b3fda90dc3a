"""Region queries ``port`` and ``tip_load``, planar and spatial: the largest error size for which
every tip of a box region stays robustly reachable with worst-case ``||G|| < 1``.

The error sets are nested families ``S(e)`` (segments, disks/balls, load ranges/discs that grow
with ``e``), so the criterion is monotone in ``e`` and is bisected per tip (:func:`._bisect_vec`).
The worst case over ``S(e)`` at each tip is a sample grid of the set plus a pattern search from each
tip's worst sample (:func:`_set_worst`). Region grids are refined (nested, spacing halved) until
the answer changes by less than ``REFINE_TOL``.

Physics: in the plane, :class:`errplan.fields.Evaluator` (the numpy model; P2's flexion controller
too); in 3-D, :class:`errplan.fields.KernelEvaluator` (the compiled kernels' ``M = J Jhat^-1`` of
one instance, rigid controller) with ``||G||`` the largest singular value of ``I - k M``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from ..errors import ErrplanError, InfeasibleError
from ..fields import ErrorSet, Evaluator
from ..inputs import memory_budget
from ..kinematics.arm import Arm
from ..metrics import g_norm_from_parts
from .result import Progress
from .search import _bisect_vec

#: Relative change of an answer under grid refinement that we accept (the issue's 1%).
REFINE_TOL = 0.01
#: memory (bytes) per region tip while a worst case over an error set is evaluated (measured with
#: tracemalloc at about 350 B for the rigid controller; the flexion controller and the bisection
#: state need more)
TIP_BYTES = 2048
ALL_AXES = ("x", "y", "z")


# ============================================================================= region grids
def region_axes(region: dict) -> tuple[str, ...]:
    """The axes of a region table in point order: ``("y", "z")`` or ``("x", "y", "z")``."""
    return tuple(a for a in ALL_AXES if a in region)


def region_text(region: dict) -> str:
    """``{y = [lo, hi], z = [lo, hi]}`` (as the scenario writes it), for messages."""
    return "{" + ", ".join(f"{a} = {list(region[a])}" for a in region_axes(region)) + "}"


def point_text(p) -> str:
    return "[" + ", ".join(f"{float(v):.4f}" for v in p) + "]"


def _grid_size(region: dict, spacing: float) -> tuple[float, ...]:
    """:func:`_grid_counts` as floats, computed without building anything (a size check first)."""
    out = []
    for key in region_axes(region):
        lo, hi = region[key]
        out.append(1.0 if hi == lo else max(2.0, math.ceil((hi - lo) / spacing - 1e-9) + 1.0))
    return tuple(out)


def _grid_counts(region: dict, spacing: float) -> tuple[int, ...]:
    out = []
    for key in region_axes(region):
        lo, hi = region[key]
        out.append(1 if hi == lo else max(2, int(math.ceil((hi - lo) / spacing - 1e-9)) + 1))
    return tuple(out)


def _grid(region: dict, counts: tuple[int, ...]) -> np.ndarray:
    axes = [np.linspace(region[key][0], region[key][1], n) for key, n in zip(region_axes(region), counts)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=-1)


def region_grid(region: dict, spacing: float) -> np.ndarray:
    """Tips (m, d) on a grid over ``region = {[x: [lo, hi],] y: [lo, hi], z: [lo, hi]}`` with edges
    included and spacing at most ``spacing``."""
    from ..inputs import check_allocation

    size = _grid_size(region, spacing)
    d = len(size)
    check_allocation("spacing", spacing, math.prod(size), d * 8 * 3, "the region grid")
    return _grid(region, _grid_counts(region, spacing))


def _spacing(region: dict, counts: tuple[int, ...]) -> float:
    s = [(region[key][1] - region[key][0]) / (n - 1) for key, n in zip(region_axes(region), counts) if n > 1]
    return float(max(s)) if s else 0.0


def _extent(region: dict) -> float:
    return max(region[a][1] - region[a][0] for a in region_axes(region))


# ============================================================================= nested error sets
@dataclass
class _OffsetSet:
    """A planar nested family of error sets ``theta(e) = (dy, dz, t)`` parametrised by a size ``e``.

    ``shape``: ``"y"`` / ``"z"`` (segment ``[-e, e]`` along that axis), ``"radial"`` (disk radius
    ``e``), ``"load"`` (tip load ``t in [-e, e]`` with a fixed port box). The set is parametrised by
    ``q`` in a unit box; ``theta(q, e)`` maps it.
    """

    shape: str
    t_range: tuple[float, float] = (0.0, 0.0)
    box_y: tuple[float, float] = (0.0, 0.0)
    box_z: tuple[float, float] = (0.0, 0.0)

    def unit_samples(self) -> np.ndarray:
        t = np.linspace(0, 1, 5) if self.t_range[1] > self.t_range[0] else np.array([0.0])
        if self.shape in ("y", "z"):
            grid = [np.linspace(-1, 1, 9), t]
        elif self.shape == "radial":
            grid = [np.linspace(0, 1, 4), np.arange(24) / 24.0, t]
        else:  # load
            by = np.linspace(0, 1, 3) if self.box_y[1] > self.box_y[0] else np.array([0.0])
            bz = np.linspace(0, 1, 3) if self.box_z[1] > self.box_z[0] else np.array([0.0])
            grid = [np.linspace(-1, 1, 9), by, bz]
        q = np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1).reshape(-1, len(grid))
        if self.shape == "radial":  # the centre once per load sample
            q = np.concatenate([q[q[:, 0] > 0], np.stack([np.zeros_like(t), np.zeros_like(t), t], axis=-1)])
        return q

    def steps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Initial pattern steps, lower and upper bounds of ``q`` (the angle of a disk wraps)."""
        if self.shape in ("y", "z"):
            return np.array([0.25, 0.25]), np.array([-1.0, 0.0]), np.array([1.0, 1.0])
        if self.shape == "radial":
            return np.array([1 / 6, 1 / 48, 0.25]), np.array([0.0, -np.inf, 0.0]), np.array([1.0, np.inf, 1.0])
        return np.array([0.25, 0.25, 0.25]), np.array([-1.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0])

    def active(self) -> np.ndarray:
        t_on = self.t_range[1] > self.t_range[0]
        if self.shape in ("y", "z"):
            return np.array([True, t_on])
        if self.shape == "radial":
            return np.array([True, True, t_on])
        return np.array([True, self.box_y[1] > self.box_y[0], self.box_z[1] > self.box_z[0]])

    def theta(self, q: np.ndarray, e: np.ndarray) -> np.ndarray:
        """``theta`` (..., 3) for ``q`` (..., k) and sizes ``e`` (...)."""
        t0, t1 = self.t_range
        if self.shape in ("y", "z"):
            d = e * q[..., 0]
            t = t0 + (t1 - t0) * q[..., 1]
            z0 = np.zeros_like(d)
            return np.stack([d, z0, t] if self.shape == "y" else [z0, d, t], axis=-1)
        if self.shape == "radial":
            ang = 2 * np.pi * q[..., 1]
            rad = e * q[..., 0]
            t = t0 + (t1 - t0) * q[..., 2]
            return np.stack([rad * np.sin(ang), rad * np.cos(ang), t], axis=-1)
        dy = self.box_y[0] + (self.box_y[1] - self.box_y[0]) * q[..., 1]
        dz = self.box_z[0] + (self.box_z[1] - self.box_z[0]) * q[..., 2]
        return np.stack([dy, dz, e * q[..., 0]], axis=-1)


#: load directions sampled around the shaft (the fields' kernels sample max(8, samples))
PSI_SAMPLES = 8


@dataclass
class _SpatialSet:
    """A spatial nested family ``theta(e) = (dx, dy, dz, tau, psi)`` (the kernels' parameters: port
    offset, lateral load magnitude ``tau`` (1/m^2) and its direction ``psi`` around the shaft).

    ``shape``: ``"x"``, ``"y"``, ``"z"`` (the segment ``[-e, e]`` along that axis), ``"radial"``
    (the ball of radius ``e``), with a load magnitude in ``t_range`` in any direction; or ``"load"``
    (the lateral-load disc: magnitude ``tau in [0, e]``, any direction) with a fixed port box
    ``box`` (three ``(lo, hi)`` offsets).

    Unit parameters ``q``: segment ``[s in [-1, 1], qt, qpsi]``; ball ``[r in [0, 1], c = cos of
    the polar angle from +z in [-1, 1], v = azimuth / 2 pi (periodic), qt, qpsi]``; load ``[qtau in
    [0, 1], qpsi, bx, by, bz]``, with ``tau = t0 + (t1 - t0) qt`` and ``psi = 2 pi qpsi`` (periodic).
    """

    shape: str
    t_range: tuple[float, float] = (0.0, 0.0)
    box: tuple[tuple[float, float], ...] = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))

    def _load_axes(self) -> list[np.ndarray]:
        t0, t1 = self.t_range
        qt = np.linspace(0, 1, 3) if t1 > t0 else np.array([0.0])
        qpsi = np.arange(PSI_SAMPLES) / PSI_SAMPLES if t1 > 0 else np.array([0.0])
        return [qt, qpsi]

    def unit_samples(self) -> np.ndarray:
        if self.shape in ("x", "y", "z"):
            grid = [np.linspace(-1, 1, 9)] + self._load_axes()
            return np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1).reshape(-1, 3)
        if self.shape == "radial":
            # 26 directions (3 latitudes x 8 azimuths and the poles) on 2 radii, and the centre
            dirs = [(c, v) for c in (-0.5, 0.0, 0.5) for v in np.arange(8) / 8] + [(-1.0, 0.0), (1.0, 0.0)]
            pts = [(r, c, v) for r in (0.5, 1.0) for c, v in dirs] + [(0.0, 0.0, 0.0)]
            qt, qpsi = self._load_axes()
            out = [(*p, a, b) for p in pts for a in qt for b in qpsi]
            return np.array(out, float)
        qtau = np.linspace(-1, 1, 9)[4:]  # [0, 1] in 5 steps
        qpsi = np.arange(PSI_SAMPLES) / PSI_SAMPLES
        bs = [np.linspace(0, 1, 3) if hi > lo else np.array([0.0]) for lo, hi in self.box]
        grid = [qtau, qpsi] + bs
        return np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1).reshape(-1, 5)

    def steps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        inf = np.inf
        p = 0.5 / PSI_SAMPLES
        if self.shape in ("x", "y", "z"):
            return np.array([0.25, 0.25, p]), np.array([-1.0, 0.0, -inf]), np.array([1.0, 1.0, inf])
        if self.shape == "radial":
            return (np.array([0.25, 0.25, 1 / 16, 0.25, p]), np.array([0.0, -1.0, -inf, 0.0, -inf]),
                    np.array([1.0, 1.0, inf, 1.0, inf]))
        return np.array([0.125, p, 0.25, 0.25, 0.25]), np.array([0.0, -inf, 0.0, 0.0, 0.0]), np.array([1.0, inf, 1.0, 1.0, 1.0])

    def active(self) -> np.ndarray:
        t0, t1 = self.t_range
        if self.shape in ("x", "y", "z"):
            return np.array([True, t1 > t0, t1 > 0])
        if self.shape == "radial":
            return np.array([True, True, True, t1 > t0, t1 > 0])
        return np.array([True, True] + [hi > lo for lo, hi in self.box])

    def theta(self, q: np.ndarray, e: np.ndarray) -> np.ndarray:
        """``theta`` (..., 5) for ``q`` (..., k) and sizes ``e`` (...)."""
        t0, t1 = self.t_range
        e = np.asarray(e, float)
        if self.shape == "load":
            tau = e * q[..., 0]
            psi = 2 * np.pi * q[..., 1]
            offs = [lo + (hi - lo) * q[..., 2 + i] for i, (lo, hi) in enumerate(self.box)]
            return np.stack(offs + [tau, psi], axis=-1)
        if self.shape in ("x", "y", "z"):
            d = e * q[..., 0]
            zero = np.zeros_like(d)
            offs = [d if a == self.shape else zero for a in ALL_AXES]
            qt, qpsi = q[..., 1], q[..., 2]
        else:
            rad = e * q[..., 0]
            c = np.clip(q[..., 1], -1.0, 1.0)
            s = np.sqrt(1.0 - c * c)
            v = 2 * np.pi * q[..., 2]
            offs = [rad * s * np.cos(v), rad * s * np.sin(v), rad * c]
            qt, qpsi = q[..., 3], q[..., 4]
        tau = t0 + (t1 - t0) * qt
        psi = 2 * np.pi * qpsi
        return np.stack(offs + [np.broadcast_to(tau, offs[0].shape), np.broadcast_to(psi, offs[0].shape)], axis=-1)


# ============================================================================= physics of one instance
class _PlanarPhysics:
    """``||G||`` of one planar error instance per tip (numpy :class:`errplan.fields.Evaluator`)."""

    def __init__(self, ev: Evaluator):
        self.ev = ev

    def g(self, x: np.ndarray, th: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
        """Worst ``||G||`` (inf where the model is invalid) and reachability alone, per tip."""
        mu, nu, ok = self.ev.parts(x, th)
        _, okr = self.ev.true_wrist(x, th)
        g = g_norm_from_parts(mu, nu, k).max(axis=-1)
        return np.where(ok, g, np.inf), okr


class _SpatialPhysics:
    """``||G||`` of one spatial error instance per tip: the compiled kernels' ``M = J Jhat^-1``
    (:meth:`errplan.fields.KernelEvaluator.motion_maps`, rigid lever through the estimate, the true
    port ``base + (dx, dy, dz)``, the flexed shaft under a lateral load) and the largest singular
    value of ``I - k M``; for P2's flexion controller in 3-D (``jacobian = "flexion"``) the maps of
    :class:`errplan.fields.SpatialFlexionEvaluator` and the worst over its noise corners. The kernel reports one validity flag (reachable and a regular controller
    Jacobian), so reachability here is that flag."""

    def __init__(self, sc, base_port, jacobian: str = "rigid"):
        from ..fields import KernelEvaluator, SpatialFlexionEvaluator
        from ..scenario import Port, Uncertainty

        # No error box: the evaluator's true port is ``port.position`` = base; instances give offsets.
        noise = sc.uncertainty.sensor_noise if jacobian == "flexion" else None
        sc0 = sc.with_(effects={}, port=Port(tuple(float(v) for v in base_port), tuple(sc.port.estimate)),
                      uncertainty=Uncertainty(sensor_noise=noise, samples=sc.uncertainty.samples),
                      controller=replace(sc.controller, jacobian=jacobian))
        # P2's flexion controller in 3-D: the numpy evaluator, the worst over its noise corners
        from ..models import build_arm

        self.fev = SpatialFlexionEvaluator.from_model(build_arm(sc0)) if jacobian == "flexion" else None
        self.kev = None if self.fev is not None else KernelEvaluator(sc0)

    def g(self, x: np.ndarray, th: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
        if self.fev is not None:
            x, th = np.asarray(x, float), np.asarray(th, float)
            shape = np.broadcast_shapes(x.shape[:-1], th.shape[:-1])
            M, _, ok = self.fev.parts(np.broadcast_to(x, shape + (3,)).reshape(-1, 3),
                                      np.broadcast_to(th, shape + th.shape[-1:]).reshape(-1, th.shape[-1]))
            G = np.eye(3) - k * np.where(ok[:, None, None, None], M, 0.0)
            g = np.linalg.norm(G, 2, axis=(-2, -1)).max(axis=-1)
            return np.where(ok, g, np.inf).reshape(shape), ok.reshape(shape)
        M, ok = self.kev.motion_maps(x, th)
        G = np.eye(3) - k * np.where(ok[..., None, None], M, 0.0)
        g = np.linalg.norm(G, 2, axis=(-2, -1))
        return np.where(ok, g, np.inf), ok


def _set_worst(phys, x: np.ndarray, oset, e: np.ndarray, k: float,
               levels: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Worst ``||G||`` over ``oset(e_i)`` at tips ``x_i`` (n,), validity (every evaluated instance
    reachable and the controller model regular) and reachability alone (n,)."""
    if isinstance(phys, Evaluator):
        phys = _PlanarPhysics(phys)
    n = len(x)
    Q = oset.unit_samples()
    best = np.full(n, -np.inf)
    qbest = np.zeros((n, Q.shape[1]))
    valid = np.ones(n, bool)
    reach = np.ones(n, bool)

    def evaluate(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return phys.g(x, oset.theta(q, e), k)

    for q in Q:
        g, okr = evaluate(np.broadcast_to(q, (n, len(q))))
        reach &= okr
        valid &= np.isfinite(g)
        upd = g > best
        best[upd] = g[upd]
        qbest[upd] = q
    step0, qlo, qhi = oset.steps()
    act = oset.active()
    for level in range(levels):
        h = step0 * 2.0 ** (-level)
        for dim in np.flatnonzero(act):
            for sgn in (-1.0, 1.0):
                c = qbest.copy()
                c[:, dim] = np.clip(c[:, dim] + sgn * h[dim], qlo[dim], qhi[dim])
                g, okr = evaluate(c)
                reach &= okr
                valid &= np.isfinite(g)
                upd = g > best
                best[upd] = g[upd]
                qbest[upd] = c[upd]
    return best, valid, reach


# ============================================================================= the region bisection
def _region_tolerance(ev, region: dict, oset, k: float, *, cap: float, start: float,
                      unit: str, spacing: float | None, label: str, progress: Progress | None = None
                      ) -> dict[str, Any]:
    """Largest size with ``||G|| < 1`` and reachability over a region: per-tip bisection on an
    initial grid, then nested refinements (each halves the spacing, keeping the old tips) until the
    answer changes by less than ``REFINE_TOL``. A refinement only bisects the new tips that fail at
    the current answer (the others cannot lower the minimum), so it costs about one evaluation."""
    from ..inputs import check_allocation

    ext = _extent(region)
    h = float(spacing) if spacing else ext / 8.0
    hh = min(h, ext) if ext > 0 else 1.0
    size = _grid_size(region, hh)
    key, value = ("spacing", h) if spacing else ("region", region_text(region))
    check_allocation(key, value, math.prod(size), TIP_BYTES,
                     f"the region grid ({' x '.join(f'{n:.3g}' for n in size)} tips at "
                     f"{min(h, ext) if ext > 0 else 0.0:g} m)")
    counts = _grid_counts(region, hh)
    x = _grid(region, counts)
    g0, ok0, r0 = _set_worst(ev, x, oset, np.zeros(len(x)), k)
    where = f"region = {region_text(region)}"
    if not r0.all():
        bad = x[~r0][0]
        raise InfeasibleError(f"{where}: the tip {point_text(bad)} is outside the workspace even without "
                              f"error ({int((~r0).sum())} of {len(x)} grid tips unreachable)")
    if not ok0.all():
        bad = x[~ok0][0]
        raise InfeasibleError(f"{where}: the controller's model is singular or unidentifiable at "
                              f"{point_text(bad)} even without error")

    def fails_at(xs: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        def fails(e: np.ndarray) -> np.ndarray:
            g, ok, _ = _set_worst(ev, xs, oset, e, k)
            return ~ok | (g >= 1.0)
        return fails

    lo, hi, capped = _bisect_vec(fails_at(x), len(x), start, cap, zero_fails=g0 >= 1.0, progress=progress,
                                 label=label)
    j = int(np.argmin(lo))
    best = {"value": float(lo[j]), "upper": float(hi[j]), "point": x[j], "zero": bool(g0[j] >= 1.0),
            "capped": bool(capped[j])}
    per_tip = {"points": x, unit: lo}
    x0 = x
    change, refinements = (0.0 if ext == 0 else None), 0
    while ext > 0 and refinements < 6 and best["value"] > 0 and not best["capped"]:
        fine = tuple(2 * n - 1 if n > 1 else 1 for n in counts)
        if float(math.prod(fine)) * TIP_BYTES > memory_budget():
            break  # the machine cannot hold a finer grid: the answer stays unconverged (reported)
        xf = _grid(region, fine)
        old = np.zeros(fine, bool)
        old[tuple(slice(None, None, 2 if f > 1 else 1) for f in fine)] = True
        xn = xf[~old.ravel()]
        v = best["value"]
        fails = fails_at(xn)
        f_new = fails(np.full(len(xn), v))
        new_value = v
        if f_new.any():
            xs = xn[f_new]
            g0n, _, r0n = _set_worst(ev, xs, oset, np.zeros(len(xs)), k)
            if not r0n.all():
                bad = xs[~r0n][0]
                raise InfeasibleError(f"{where}: the tip {point_text(bad)} is outside the workspace even "
                                      "without error")
            lo_n, hi_n, _ = _bisect_vec(fails_at(xs), len(xs), v, v, zero_fails=g0n >= 1.0)
            jn = int(np.argmin(lo_n))
            if lo_n[jn] < v:
                new_value = float(lo_n[jn])
                best = {"value": new_value, "upper": float(hi_n[jn]), "point": xs[jn], "zero": bool(g0n[jn] >= 1.0),
                        "capped": False}
        change = (v - new_value) / v
        counts, x = fine, xf
        refinements += 1
        if change < REFINE_TOL:
            break
    # why the binding tip fails just above the answer
    xb = best["point"][None, :]
    gb, okb, rb = _set_worst(ev, xb, oset, np.array([best["upper"]]), k)
    reason = ("G_norm" if best["zero"] else "capped" if best["capped"] else
              "reachability" if not rb[0] else "singular" if not okb[0] else "G_norm")
    # plot-ready curve: size vs max over the region of the worst ||G|| (and whether every tip is
    # valid), on the initial grid plus the binding tip
    top = best["value"] if best["capped"] else max(2.0 * best["value"], start)
    sizes = np.linspace(0.0, top, 41)
    gmax, allok = [], []
    xc = np.concatenate([x0, xb])
    for e in sizes:
        g, ok, _ = _set_worst(ev, xc, oset, np.full(len(xc), e), k)
        gmax.append(float(np.max(g[ok])) if ok.any() else float("nan"))
        allok.append(bool(ok.all()))
    return {"value": best["value"], "upper": best["upper"], "binding_point": best["point"], "binding": reason,
            "tips": len(x), "spacing": _spacing(region, counts), "refinements": refinements,
            "refinement_change": change, "converged": bool(change is not None and change < REFINE_TOL),
            "curve": {unit: sizes, "max_G_norm": gmax, "all_valid": allok}, "per_tip_map": per_tip}


# ============================================================================= the queries
def _evaluator(sc, jacobian: str, base_port, t_range=(0.0, 0.0)) -> Evaluator:
    """The planar numpy physics with the true port ``base_port + offset`` (offsets from the queries)."""
    u = sc.uncertainty
    noise = (u.sensor_noise.position, u.sensor_noise.angle) if (u.sensor_noise and jacobian == "flexion") else (0.0, 0.0)
    es = ErrorSet(tuple(base_port), (0.0, 0.0, t_range[0]), (0.0, 0.0, t_range[1]), noise, 5)
    return Evaluator(Arm.from_robot(sc.robot), sc.instrument.length, tuple(sc.port.estimate), jacobian, es)


def _load_range(v, default) -> tuple[float, float]:
    if v is None:
        return default
    if isinstance(v, (tuple, list)):
        return (float(v[0]), float(v[1]))
    return (float(v), float(v))


def _check_region(sc, region: dict) -> None:
    want = ALL_AXES[3 - sc.dim:]
    if set(region) != set(want):
        form = "{ " + ", ".join(f"{a} = [lo, hi]" for a in want) + " }"
        raise ErrplanError(f"region = {region_text(region)}: expected {form} (a {sc.dim}-D region)")


def port_tolerance(sc, region: dict, direction_: str = "radial", *, gain: float | None = None,
                   tip_force_over_ei=None, spacing: float | None = None,
                   progress: Progress | None = None) -> dict[str, Any]:
    """Largest port error (m) in ``direction_`` keeping the region reachable and worst ``||G|| < 1``.

    The true port ranges over ``port.estimate + S(e)``: the segment ``[-e, e]`` along an axis
    (``"y"``, ``"z"``, and ``"x"`` in 3-D) or the disk (planar) / ball (spatial) of radius ``e``
    (``"radial"``). The tip load is ``tip_force_over_ei`` (a number: that load; a pair: the worst
    case over the range; default the scenario's ``[uncertainty] tip_force_over_ei`` range, else 0);
    in 3-D it is a lateral load magnitude, in every direction normal to the shaft. Returns
    ``value``, ``binding_point``, ``binding`` (``"G_norm"`` or ``"reachability"``), the grid used
    and the curve ``error`` vs ``max_G_norm``.
    """
    d = sc.dim
    allowed = ("x", "y", "z", "radial") if d == 3 else ("y", "z", "radial")
    if direction_ not in allowed:
        raise ErrplanError(f"direction = {direction_!r}: expected " + ", ".join(f'"{a}"' for a in allowed[:-1])
                           + " or \"radial\"" + (" (\"x\" only in a spatial scenario)" if direction_ == "x" else ""))
    _check_region(sc, region)
    k = float(gain if gain is not None else sc.controller.gain)
    t_range = _load_range(tip_force_over_ei, sc.uncertainty.tip_force_over_ei or (0.0, 0.0))
    if d == 3:
        if t_range[0] < 0 or t_range[1] < t_range[0]:
            raise ErrplanError(f"tip_force_over_ei = {list(t_range)}: expected a lateral load magnitude "
                               "(a number >= 0 or [lo, hi] with 0 <= lo <= hi) in a spatial scenario")
        if sc.controller.jacobian == "flexion" and t_range[0] <= 0:
            raise ErrplanError(f"tip_force_over_ei = {list(t_range)}: P2's flexion controller cannot identify its "
                               "model without flexion; give a load magnitude range above 0")
        ev: Any = _SpatialPhysics(sc, sc.port.estimate, sc.controller.jacobian)
        oset: Any = _SpatialSet(direction_, t_range)
    else:
        if sc.controller.jacobian == "flexion" and t_range[0] <= 0 <= t_range[1]:
            raise ErrplanError(f"tip_force_over_ei = {list(t_range)}: P2's flexion controller cannot identify its "
                               "model without flexion; give a non-zero tip load (or a range that excludes 0)")
        ev = _evaluator(sc, sc.controller.jacobian, sc.port.estimate, t_range)
        oset = _OffsetSet(direction_, t_range)
    res = _region_tolerance(ev, region, oset, k, cap=sc.instrument.length, start=0.001, unit="error",
                            spacing=spacing, label="port tolerance", progress=progress)
    return {"value": res["value"], "binding_point": res["binding_point"], "binding": res["binding"],
            "direction": direction_, "gain": k, "tip_force_over_ei": list(t_range), "region": region,
            "controller": sc.controller.jacobian, "grid": {"tips": res["tips"], "spacing": res["spacing"]},
            "refinement_change": res["refinement_change"], "converged": res["converged"],
            "bracket": [res["value"], res["upper"]], "curve": res["curve"], "per_tip": res["per_tip_map"]}


def tip_load_tolerance(sc, region: dict, *, gain: float | None = None, port_y=None, port_z=None,
                       port_x=None, spacing: float | None = None, progress: Progress | None = None) -> dict[str, Any]:
    """Largest ``T`` (1/m^2) such that the rigid-lever controller through ``port.estimate`` keeps
    worst ``||G|| < 1`` and the region reachable for every tip load in ``[-T, T]`` (planar; in 3-D
    every lateral load of magnitude at most ``T``: the disc normal to the shaft), and every true
    port in ``estimate + [port_x x] port_y x port_z`` when a box is given (else the true port is
    ``port.position``)."""
    d = sc.dim
    _check_region(sc, region)
    if d == 2 and port_x is not None:
        raise ErrplanError("port_x: only in a spatial scenario")
    k = float(gain if gain is not None else sc.controller.gain)
    given = [port_x, port_y, port_z] if d == 3 else [port_y, port_z]
    if all(b is None for b in given):
        base, boxes = sc.port.position, [(0.0, 0.0)] * d
    else:
        base, boxes = sc.port.estimate, [tuple(b or (0.0, 0.0)) for b in given]
    if d == 3:
        ev: Any = _SpatialPhysics(sc, base)
        oset: Any = _SpatialSet("load", box=tuple(boxes))
    else:
        ev = _evaluator(sc, "rigid", base)
        oset = _OffsetSet("load", box_y=boxes[0], box_z=boxes[1])
    res = _region_tolerance(ev, region, oset, k, cap=1000.0, start=0.5, unit="tip_force_over_ei",
                            spacing=spacing, label="tip-load tolerance", progress=progress)
    out = {"value": res["value"], "binding_point": res["binding_point"], "binding": res["binding"],
           "gain": k, "region": region, "controller": "rigid", "true_port": list(base)}
    if d == 3:
        out["port_x"] = list(boxes[0])
    out.update({"port_y": list(boxes[-2]), "port_z": list(boxes[-1]),
                "grid": {"tips": res["tips"], "spacing": res["spacing"]},
                "refinement_change": res["refinement_change"], "converged": res["converged"],
                "bracket": [res["value"], res["upper"]], "curve": res["curve"], "per_tip": res["per_tip_map"]})
    return out
