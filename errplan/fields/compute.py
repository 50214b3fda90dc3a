"""``compute_fields``: a scenario's worst-case fields on its tip grid, tile by tile.

The grid covers the scenario's ``[fields] region`` or, without one, the bounding box of every tip
some corner instance of the error set reaches. Tips farther than the shaft length from some
corner port cannot be robustly valid and are skipped. The rest is split into tiles, each an
independent task (:func:`errplan.cluster.map_tasks`: in process, local worker processes or a
dask cluster, identical arrays either way). A tile runs the compiled kernel
(:mod:`.kernels`) for the rigid controller without Jacobian-changing effects, in the plane and in
3-D, and the numpy search (:mod:`.search`) for P2's flexion controller (in 3-D over compiled physics,
:mod:`.kernels.flexion`) or a truth with ``[effects]`` that change J, Jhat or the loop's frame (the arm's
geometry, the instrument's length, a tracker registration, joint offsets, gravity sag, a world load).
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ErrplanError
from ..metrics import phi_hat_max
from ..errorset import ErrorSet, error_set
from .grid import MetricField
from .search import EXTRA_PASSES, REFINE_LEVELS, SECOND_START, Progress, _refined_at_gain, minimize_gain, worst_case

DEFAULT_METRICS = ("G_norm", "phi_hat_max", "phi_max")
ALL_METRICS = ("G_norm", "phi_hat_max", "phi_max", "rho_star")
TILE_POINTS = 4096  # tips per tile at least (tens of ms of compiled work)...
TILE_POINTS_MAX = 16384  # ...and at most; in between, about 16 tiles per worker (each tile costs a kernel
# dispatch and a result shipped back: at 0.25 mm over P1's workspace 674 tiles of 4096 took 2.6 s on 2
# workers, 169 of 16384 2.1 s). A tip's values do not depend on its tile.
BYTES_PER_POINT = 96  # grid coordinates, flags and the output arrays, per grid point
MAX_GRID_POINTS = 4_000_000  # a larger grid is a mistake more often than a wish: one clear error


def parse_metrics(text: str | None, rho_star: bool = False) -> tuple[str, ...]:
    """``--metrics`` (comma-separated subset of ALL_METRICS; default the first three) plus ``--rho-star``."""
    if text is None:
        names = list(DEFAULT_METRICS)
    else:
        names = [t.strip() for t in text.split(",") if t.strip()]
        bad = [t for t in names if t not in ALL_METRICS]
        if bad or not names:
            raise ErrplanError(f"--metrics = {text!r}: expected a comma-separated subset of {','.join(ALL_METRICS)}")
    if rho_star and "rho_star" not in names:
        names.append("rho_star")
    return tuple(n for n in ALL_METRICS if n in names)


# ----------------------------------------------------------------------------- the grid
def _axis_range(lo: float, hi: float, res: float, inside: bool) -> tuple[int, int]:
    """Index range ``(i0, i1)`` of the multiples of ``res`` covering [lo, hi] (``inside``: only those
    within it). Plain integers: nothing is allocated before the size is checked."""
    if inside:
        return math.ceil(lo / res - 1e-9), math.floor(hi / res + 1e-9)
    return math.floor(lo / res), math.ceil(hi / res)


def _load_max(es: ErrorSet) -> float:
    d = es.dim
    return float(max(abs(es.lo[d]), abs(es.hi[d])))


def workspace_bounds(sc, es: ErrorSet) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box ``(lo, hi)`` (d,) of the tips some corner port of the error set lets a reachable
    wrist put through it, padded by the largest deflection a declared load can add."""
    from ..kinematics import arm_for
    from ..kinematics.shaft import flexed_tip

    arm = arm_for(sc.robot)
    L = sc.instrument.length
    w = arm.sample_wrists(161 if sc.dim == 2 else 41)
    tips = []
    tmax = _load_max(es)
    for port in es.port_corners():
        r = np.linalg.norm(port - w, axis=-1)
        ww = w[(r < L) & (r > 1e-6)]
        if not len(ww):
            continue
        if sc.dim == 2:  # the planar beam at the load corners, as before
            for t in {es.lo[2], es.hi[2]}:
                tips.append(flexed_tip(ww, port, L, t))
        else:
            d = port - ww
            tips.append(ww + L * d / np.linalg.norm(d, axis=-1, keepdims=True))
    if not tips:
        raise ErrplanError(f"{sc.source}: the tip workspace is empty: no reachable wrist puts the shaft through the port")
    t = np.concatenate(tips)
    pad = L * math.atan(tmax * L * L / 3.0) if sc.dim == 3 else 0.0
    return t.min(axis=0) - pad, t.max(axis=0) + pad


def tip_grid(sc, es: ErrorSet, res: float) -> tuple[np.ndarray, ...]:
    """Grid axes (d of them): the scenario's region, else the padded workspace bounding box."""
    from ..inputs import check_allocation

    region = sc.fields.region
    if region:
        spans = [_axis_range(*region[a], res, True) for a in sc.axes]
        for a, (i0, i1) in zip(sc.axes, spans):
            if i1 < i0:
                raise ErrplanError(f"{sc.source}: [fields] region.{a} = {list(region[a])}: holds no grid point at "
                                   f"resolution {res} m (an empty region)")
    else:
        lo, hi = workspace_bounds(sc, es)
        spans = [_axis_range(l - 2 * res, h + 2 * res, res, False) for l, h in zip(lo, hi)]
    counts = [i1 - i0 + 1 for i0, i1 in spans]
    n = math.prod(counts)
    check_allocation("[fields] resolution", res, n, BYTES_PER_POINT, "tip grid")
    if n > MAX_GRID_POINTS:
        raise ErrplanError(f"resolution = {res}: the grid would have {n:,} points ({' x '.join(map(str, counts))}; "
                           f"max {MAX_GRID_POINTS:,}): use a coarser resolution or a [fields] region")
    return tuple(np.arange(i0, i1 + 1) * res for i0, i1 in spans)


# ----------------------------------------------------------------------------- tiles
@dataclass(frozen=True)
class FieldJob:
    """Everything a tile needs (picklable: shipped once to each cluster worker)."""

    X: np.ndarray  # (n, d) candidate tips
    k: float
    want_phi: bool
    want_rho: bool
    refine: int
    samples: int | None
    kernel: dict[str, Any] | None  # compiled path: the kernel's array arguments
    evaluator: Any = None  # numpy path: a fields.evaluator.Evaluator


def run_tile(job: FieldJob, span: tuple[int, int]) -> dict[str, np.ndarray]:
    """Worst case on tips ``job.X[i0:i1]``: ``valid``, ``G_norm``, ``phi_max``, ``rho_star``, ``k_star``."""
    i0, i1 = span
    X = np.ascontiguousarray(job.X[i0:i1])
    if job.kernel is not None:
        from .kernels import worst_case_tile

        n = len(X)
        out = {"valid": np.zeros(n, bool), "G_norm": np.empty(n), "phi_max": np.empty(n),
               "rho_star": np.empty(n), "k_star": np.empty(n)}
        worst_case_tile(X, *_tile_args(job), out["valid"], out["G_norm"], out["phi_max"], out["rho_star"],
                        out["k_star"])
        return out
    return _numpy_tile(job.evaluator, X, job.k, job.samples, job.refine, job.want_rho)


def _tile_args(job: FieldJob) -> tuple:
    """The compiled search's arguments after the tips and before the outputs (:func:`worst_case_tile`)."""
    kk = job.kernel
    return (kk["grid"], kk["counts"], kk["active"], kk["periodic"], kk["lo"], kk["hi"], kk["step0"],
            kk["base_port"], kk["est"], kk["L"], job.k, kk["arm"], kk["chain"], kk["rmap"], job.refine,
            EXTRA_PASSES, SECOND_START, job.want_phi, job.want_rho)


def _field_tile(job: FieldJob, span: tuple[int, int]) -> dict[str, np.ndarray]:
    """:func:`run_tile` keeping only the arrays the field asked for (a worker ships less back)."""
    out = run_tile(job, span)
    drop = (() if job.want_phi else ("phi_max",)) + (() if job.want_rho else ("rho_star", "k_star"))
    return {key: a for key, a in out.items() if key not in drop}


#: bytes of kept motion maps per chunk of tips when rho* needs them (3-D flexion: instances x noise corners)
RHO_PARTS_BYTES = 200_000_000


def _numpy_tile(ev, X: np.ndarray, k: float, samples, refine: int, want_rho: bool) -> dict[str, np.ndarray]:
    noise = getattr(ev, "noise", None)
    if want_rho and noise is not None and len(X) > 1:
        # the kept maps are (tips, instances, corners, 3, 3): chunk the tips so memory stays flat
        per_tip = len(ev.errors.sample_grid(samples)) * len(noise) * 72
        step = max(1, int(RHO_PARTS_BYTES // max(per_tip, 1)))
        if step < len(X):
            parts = [_numpy_tile(ev, X[i:i + step], k, samples, refine, want_rho) for i in range(0, len(X), step)]
            return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    wc = worst_case(ev, X, k, samples=samples, refine=refine, keep_parts=want_rho)
    out = {"valid": wc["valid"], "G_norm": wc["G_norm"], "phi_max": wc["phi_max"]}
    if noise is not None and np.any(noise) and np.any(wc["valid"]) and hasattr(ev, "refine_noise"):
        # P2's controller in 3-D: the corners' worst, then a refinement over the noise set at the
        # worst instance (a lower bound still; the npz metadata says so)
        v = wc["valid"]
        g_r, _ = ev.refine_noise(X[v], wc["theta_G"][v], k)
        _, p_r = ev.refine_noise(X[v], wc["theta_phi"][v], k)
        out["G_norm"] = out["G_norm"].copy()
        out["phi_max"] = out["phi_max"].copy()
        out["G_norm"][v] = np.maximum(out["G_norm"][v], g_r)
        out["phi_max"][v] = np.maximum(out["phi_max"][v], p_r)
    n = len(X)
    rfull, kfull = np.full(n, np.nan), np.full(n, np.nan)
    if want_rho:
        v = wc["valid"]
        if wc["nu"] is None:  # motion maps: (n, m, c, d, d)
            rs, ks = minimize_gain(wc["mu"][v], None)
        else:
            mu = wc["mu"][v].reshape(int(v.sum()), -1)
            nu = wc["nu"][v].reshape(int(v.sum()), -1)
            rs, ks = minimize_gain(mu, nu)
        # Certify at k*: the refined worst case over the continuous error set at that gain.
        rs_ref = _refined_at_gain(ev, X[v], ks, samples=samples, refine=refine)
        rs_ref = np.where(ks > 0, np.maximum(rs, rs_ref), 1.0)
        # The scenario gain is a candidate too: rho* never exceeds the refined ||G|| at k.
        g_k = wc["G_norm"][v]
        use_k = g_k < rs_ref
        rs_ref, ks = np.where(use_k, g_k, rs_ref), np.where(use_k, k, ks)
        none = rs_ref >= 1.0  # no certified contraction: rho* = 1 (k -> 0), k* = 0
        rfull[v] = np.where(none, 1.0, rs_ref)
        kfull[v] = np.where(none, 0.0, ks)
    out["rho_star"], out["k_star"] = rfull, kfull
    return out


def numpy_worst_case(ev, x: np.ndarray, k: float, *, samples: int | None = None, refine: int = REFINE_LEVELS,
                     rho: bool = False) -> dict[str, np.ndarray]:
    """The numpy path's worst case at tips ``x`` (n, d) for an evaluator ``ev``: ``valid``,
    ``G_norm``, ``phi_max``, ``rho_star``, ``k_star`` (what a field tile computes)."""
    return _numpy_tile(ev, np.asarray(x, float), float(k), samples, refine, rho)


def _no_chain():
    """Placeholder chain and reachability map for the planar kernel (same numba types, never read)."""
    from ..kinematics.urdf import ChainData, ReachMap

    chain = ChainData(np.zeros((1, 4, 4)), np.zeros((1, 3)), np.zeros(1, np.int64), np.zeros((1, 1)), np.zeros(1),
                      np.zeros(1), np.zeros((2, 6)))
    like = {"origin": np.zeros(3), "h": 1.0, "shape": np.ones(3, np.int64), "state": np.zeros((1, 1, 1), np.uint8),
            "depth": np.zeros((1, 1, 1), np.uint8), "sub": 1, "seed_ptr": np.zeros(2, np.int64), "seeds": np.zeros((1, 1))}
    rmap = ReachMap(**{f: like[f] for f in ReachMap._fields})
    return chain, rmap


def _kernel_args(sc, es: ErrorSet, samples: int | None) -> dict[str, Any]:
    from ..kinematics import arm_for

    arm = arm_for(sc.robot)
    if sc.dim == 2:
        from .kernels import planar_arm_params

        arm_p = planar_arm_params(arm)
        chain, rmap = _no_chain()
    else:
        arm_p = np.zeros(16)
        chain, rmap = arm.kernel()
    return {"grid": np.ascontiguousarray(es.sample_grid(samples)), "counts": es.counts(samples),
            "active": es.active, "periodic": es.periodic, "lo": es.lo_arr, "hi": es.hi_arr,
            "step0": es.spacing(samples), "base_port": np.asarray(es.base_port, float),
            "est": np.asarray(sc.port.estimate, float), "L": float(sc.instrument.length), "arm": arm_p,
            "chain": chain, "rmap": rmap}


class KernelEvaluator:
    """The compiled physics of one error instance, batched (planar and spatial, rigid controller,
    no effect that moves the arm): ``M = J Jhat^-1`` and validity for (tip, instance) pairs, and the
    worst case over the error set at any tips. The d-generic evaluator of gains and tolerances."""

    def __init__(self, sc, samples: int | None = None):
        self.scenario = sc
        self.errors, effects = error_set(sc)
        if sc.controller.jacobian != "rigid" or effects:
            raise ErrplanError(f"{sc.source}: the compiled evaluator covers the rigid controller without "
                               f"[effects] that change the true Jacobian, the controller's or the loop's frame "
                               f"(has {sc.controller.jacobian!r}, {sorted(effects)})")
        self.dim = sc.dim
        self.length = float(sc.instrument.length)
        self.estimate = tuple(sc.port.estimate)
        self._args = _kernel_args(sc, self.errors, samples)

    def motion_maps(self, x: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M, ok)`` for tips ``x`` (..., d) under instances ``theta`` (..., na), broadcast together;
        ``M`` (..., d, d) is NaN where ``ok`` is False (unreachable, shaft not through the port,
        singular controller Jacobian)."""
        from .kernels import motion_maps

        x = np.asarray(x, float)
        theta = np.asarray(theta, float)
        if x.ndim == 2 and theta.ndim == 2 and len(x) == len(theta):  # pairs (the verification's many small calls)
            shape = x.shape[:1]
            X, TH = np.ascontiguousarray(x), np.ascontiguousarray(theta)
        else:
            shape = np.broadcast_shapes(x.shape[:-1], theta.shape[:-1])
            X = np.ascontiguousarray(np.broadcast_to(x, shape + x.shape[-1:]).reshape(-1, self.dim))
            TH = np.ascontiguousarray(np.broadcast_to(theta, shape + theta.shape[-1:]).reshape(-1, theta.shape[-1]))
        M = np.empty((len(X), self.dim, self.dim))
        ok = np.empty(len(X), bool)
        a = self._args
        motion_maps(X, TH, a["base_port"], a["est"], a["L"], a["arm"], a["chain"], a["rmap"], M, ok)
        return M.reshape(shape + (self.dim, self.dim)), ok.reshape(shape)

    def worst_case(self, x: np.ndarray, k: float, *, phi: bool = True, rho: bool = False,
                   refine: int = REFINE_LEVELS, samples: int | None = None) -> dict[str, np.ndarray]:
        """Worst case at tips ``x`` (n, d): ``valid``, ``G_norm`` (gain k), ``phi_max``, ``rho_star``, ``k_star``."""
        args = self._args if samples is None else _kernel_args(self.scenario, self.errors, samples)
        job = FieldJob(np.asarray(x, float).reshape(-1, self.dim), float(k), phi, rho, refine, samples, args)
        return run_tile(job, (0, len(job.X)))


def compute_fields(sc, resolution: float | None = None, rho_star: bool = False, *,
                   samples: int | None = None, refine: int = REFINE_LEVELS,
                   progress: Progress | None = None, metrics: tuple[str, ...] | None = None,
                   workers: int | None = 1, scheduler: str | None = None,
                   tile_points: int | None = None) -> MetricField:
    """Worst-case fields of a scenario on its tip grid (docs/interfaces.md "fields npz", "3-D fields npz").

    ``metrics``: names of ALL_METRICS to compute (default G_norm, phi_hat_max, phi_max, plus
    rho_star with ``rho_star``); ``valid`` is always computed. ``tile_points``: tips per tile (default: about 16
    tiles per worker, TILE_POINTS to TILE_POINTS_MAX). ``workers``/``scheduler``: where the
    tiles run (:func:`errplan.cluster.map_tasks`); the arrays do not depend on it.
    """
    from ..cluster import default_workers, map_tasks

    names = tuple(metrics) if metrics else parse_metrics(None, rho_star)
    if rho_star and "rho_star" not in names:
        names = names + ("rho_star",)
    want_phi = "phi_max" in names
    want_rho = "rho_star" in names
    res = float(resolution or sc.fields.resolution)
    if not (res > 0 and math.isfinite(res)):
        raise ErrplanError(f"resolution = {resolution!r}: expected a grid spacing > 0 m")
    if tile_points is not None and (isinstance(tile_points, bool) or not isinstance(tile_points, (int, np.integer))
                                    or tile_points < 1):
        raise ErrplanError(f"tile_points = {tile_points!r}: expected a whole number of tips >= 1 (or None: "
                           "about 16 tiles per worker)")
    es, jac_effects = error_set(sc)
    axes = tip_grid(sc, es, res)
    shape = tuple(len(a) for a in axes)
    n_points = math.prod(shape)
    k = float(sc.controller.gain)
    compiled = sc.controller.jacobian == "rigid" and not jac_effects
    kargs = _kernel_args(sc, es, samples) if compiled else None
    loader, load_errors = None, []
    if compiled:
        # The kernel is loaded from the disk cache (or compiled) in a thread while the grid is filtered
        # below, before any worker forks: one load or compile for all of them and one first-run notice
        # (errplan.jit). numba's load runs much of its time outside the GIL (LLVM), the filter in numpy.
        first = FieldJob(np.array([[a[0] for a in axes]], float), k, want_phi, want_rho, refine, samples, kargs)

        def load():
            try:
                run_tile(first, (0, 1))
                from .kernels import load_lanes

                load_lanes(first.X.shape[1], *_tile_args(first))  # where the error set needs them
            except BaseException as e:  # raised in the caller's thread, below
                load_errors.append(e)

        loader = threading.Thread(target=load, daemon=True)
        loader.start()
    # Cheap prefilter: a robustly valid tip is within the shaft length of every port of the box,
    # in particular of its corners (the same strict test each instance applies). The squared distance
    # is summed axis by axis over the grid's broadcast axes (the same sum, term by term, as over the
    # points' coordinates, without forming them all).
    L = sc.instrument.length
    near = np.ones(shape, bool)
    d2 = np.empty(shape)  # one buffer for every corner
    for port in es.port_corners():
        sq = [((a - port[i]) ** 2).reshape([-1 if j == i else 1 for j in range(len(axes))])
              for i, a in enumerate(axes)]
        np.add(sq[0], sq[1], out=d2)
        for t in sq[2:]:
            d2 += t
        np.sqrt(d2, out=d2)
        near &= d2 < L
    cand = np.flatnonzero(near)

    def points(mask: np.ndarray) -> np.ndarray:
        """The tips (n, d) where the grid mask ``mask`` (shape) holds, in flat order."""
        return np.stack([np.broadcast_to(a.reshape([-1 if j == i else 1 for j in range(len(axes))]), shape)[mask]
                         for i, a in enumerate(axes)], axis=-1)

    Pc = points(near)
    if compiled:
        job = FieldJob(Pc, k, want_phi, want_rho, refine, samples, kargs)
    else:
        from ..models import arm_model
        from .evaluator import Evaluator, SpatialEffectsEvaluator, SpatialFlexionEvaluator

        m = arm_model(sc)  # what the top built (a scenario is built into its model here)
        if sc.dim == 2:
            ev = Evaluator.from_model(m)
        elif sc.controller.jacobian == "flexion" and not jac_effects:
            ev = SpatialFlexionEvaluator.from_model(m)
        else:
            ev = SpatialEffectsEvaluator.from_model(m)
        job = FieldJob(Pc, k, want_phi, want_rho, refine, samples, None, ev)
    if tile_points is None:
        per = len(cand) // (16 * (default_workers() if workers is None else max(1, int(workers))))
        tile_points = min(TILE_POINTS_MAX, max(TILE_POINTS, per))
    spans = [(i, min(i + tile_points, len(cand))) for i in range(0, len(cand), tile_points)]

    def tick(done, total):
        if progress:
            progress(done / total, f"tile {done}/{total}")

    if loader is not None:
        loader.join()
        if load_errors:
            raise load_errors[0]
    parts = map_tasks(_field_tile, job, spans, workers=workers, scheduler=scheduler, progress=tick)

    def scatter(key, fill=np.nan, dtype=float):
        a = np.full(n_points, fill, dtype=dtype)
        if parts:
            a[cand] = np.concatenate([p[key] for p in parts])
        return a.reshape(shape)

    valid = scatter("valid", False, bool)
    gn = scatter("G_norm")
    clearance, anatomy_meta = None, None
    extra = {}
    model = anatomy_model(sc, es)
    if model is not None:
        # The anatomy pass: a reachable tip that is not robustly clear is outside the workspace.
        clearance = np.full(shape, np.nan)
        flat = valid.reshape(-1)
        reach = np.flatnonzero(flat)
        cl = model.tip(points(valid))
        clearance.reshape(-1)[reach] = cl
        blocked = reach[cl < model.required]
        flat[blocked] = False
        gn.reshape(-1)[blocked] = np.nan
        anatomy_meta = {"clearance": model.required, "obstacles": list(model.names),
                        "blocked_points": int(len(blocked))}
        extra = {name: scatter(name) for name in ("phi_max", "rho_star", "k_star")
                 if (name == "phi_max" and want_phi) or (name != "phi_max" and want_rho)}
        for a in extra.values():
            a.reshape(-1)[blocked] = np.nan
    ph = None
    if "phi_hat_max" in names:
        ph = phi_hat_max(np.where(valid, gn, 1.0))
        ph[~valid] = np.nan
    meta = {"scenario": sc.name, "dim": sc.dim, "gain": k, "resolution": res, "jacobian": sc.controller.jacobian,
            "error_set": {"base_port": list(es.base_port), "lo": list(es.lo), "hi": list(es.hi),
                          "periodic": es.periodic.tolist(), "noise": list(es.noise),
                          "samples": samples or es.samples, "refine_levels": refine},
            "length": L, "effects": {name: dict(p) for name, p in sc.effects.items()},
            "metrics": list(names), "region": {a: list(v) for a, v in sc.fields.region.items()} if sc.fields.region
            else None}
    if sc.controller.jacobian == "flexion" and any(es.noise):
        meta["noise_worst_case"] = (
            "lower bound: the worst case over P2's sensor-noise set is taken at its corners "
            + ("(the 64 vertices of the box)" if sc.dim == 2 else
               "(position differences at -2p, 0, 2p per axis, each end direction tilted by the full angle "
               "toward 4 directions around its cone)")
            + ("" if sc.dim == 2 or jac_effects else ", then a pattern search over the noise set from the worst corner")
            + "; the worst noise can lie inside the set where ||G|| is not convex in it")
    if anatomy_meta is not None:
        meta["anatomy"] = anatomy_meta

    def get(name):
        return extra[name] if name in extra else scatter(name)

    kw = dict(meta=meta, rho_star=get("rho_star") if want_rho else None,
              k_star=get("k_star") if want_rho else None, clearance=clearance)
    if sc.dim == 3:
        kw["x"] = axes[0]
    return MetricField(axes[-2], axes[-1], valid, gn if "G_norm" in names else None, ph,
                       get("phi_max") if want_phi else None, **kw)


def anatomy_model(sc, es: ErrorSet | None = None):
    """The :class:`errplan.anatomy.ShaftClearance` of a spatial scenario's ``[anatomy]`` (obstacles and
    body wall) for the port box of its error set, or None (no anatomy, or nothing in it)."""
    if hasattr(type(sc), "true_errors") and (es is None or es == sc.true_errors):
        return sc.anatomy_model  # an errplan.models.ArmModel: built once
    an = getattr(sc, "anatomy", None)
    if an is None or (not an.obstacles and an.body_wall is None):
        return None
    from ..anatomy import build

    es = es or error_set(sc)[0]
    return build(an, es.port_corners())
