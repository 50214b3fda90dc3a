"""The gain schedule of a path (:func:`schedule_gains`, :func:`single_segment`): cut the path into segments,
sample and scan each ball, solve for the gains, verify every certificate, halve what does not certify."""
from __future__ import annotations

import math

import numpy as np

from ..errors import ErrplanError
from ..fields import Evaluator
from .certificate import _k_upper_M, _prune, _rho, _sample_segment, _scan, _scan_M, ball_clearance
from .options import GainOptions, GainSchedule, Segment
from .physics import SpatialModel, _is_spatial
from .solve import _initial_cuts, _solve_with_cuts, solve_gains
from .verify import _lower_gain, verify_segments


def cut_path(path: np.ndarray, max_segment: float) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Split every edge of ``path`` (m, 2) into equal pieces no longer than ``max_segment``."""
    path = np.asarray(path, float)
    out = []
    for e in range(len(path) - 1):
        a, b = path[e], path[e + 1]
        L = float(np.linalg.norm(b - a))
        if L <= 1e-12:
            continue
        n = max(1, math.ceil(L / max_segment - 1e-9))
        for i in range(n):
            out.append((a + (b - a) * i / n, a + (b - a) * (i + 1) / n, e))
    return out


def _as_evaluator(src):
    """The physics of a scenario: the planar :class:`Evaluator` or, in 3-D, a :class:`SpatialModel`."""
    if isinstance(src, (Evaluator, SpatialModel)):
        return src
    from ..models import arm_model

    m = arm_model(src)
    return SpatialModel.from_model(m) if m.dim == 3 else Evaluator.from_model(m)


def _default_options(src) -> GainOptions:
    if isinstance(src, SpatialModel):
        return GainOptions.for_dim(3)
    if isinstance(src, Evaluator):
        return GainOptions()
    return options_from_scenario(src)


def options_from_scenario(sc, **overrides) -> GainOptions:
    kw = {"margin": sc.planner.certify_margin}
    kw.update(overrides)
    return GainOptions.for_dim(sc.dim, **kw).validate()


def schedule_gains(src, path, options: GainOptions | None = None, *, progress=None) -> GainSchedule:
    """Certified per-segment gains for a tip path (m, 2) under a scenario's error set.

    ``src``: a :class:`errplan.scenario.Scenario` (planar or spatial), an
    :class:`errplan.fields.Evaluator` or a :class:`SpatialModel`; ``path`` (m, d).
    Cuts the path into pieces of at most ``max_segment``, halves the pieces whose ball no sampled
    gain certifies, chooses all gains in one casadi problem, verifies each certificate densely and
    halves (and re-solves) where the verification fails, up to ``rounds`` times.

    With anatomy (3-D), a piece whose convergence ball (radius = its length + ``switch_tolerance``)
    is not robustly clear (:func:`ball_clearance` < ``[anatomy] clearance``) is halved too, before
    any gain is sampled, as long as halving can help (the motion of one of its halves keeps
    ``[anatomy] clearance + switch_tolerance + min_segment``) and the floor (``max_depth`` halvings,
    ``min_segment``) allows; a ball still not clear is reported not certified with the reason.
    """
    ev = _as_evaluator(src)
    opts = (options or _default_options(src)).validate()
    dim = 3 if _is_spatial(ev) else 2
    path = np.atleast_2d(np.asarray(path, float))
    if path.ndim != 2 or path.shape[1] != dim or len(path) < 2 or not np.all(np.isfinite(path)):
        pts = "[x, y, z]" if dim == 3 else "[y, z]"
        raise ErrplanError(f"path of shape {path.shape}: expected (m >= 2, {dim}) finite {pts} points")
    pieces = [(a, b, e, 0) for a, b, e in cut_path(path, opts.max_segment)]
    if not pieces:
        raise ErrplanError("path has zero length: start and goal coincide")
    cache: dict = {}
    anatomy = getattr(ev, "anatomy", None)

    def sample(a, b):
        key = (tuple(np.round(a, 12)), tuple(np.round(b, 12)))
        if key not in cache:
            R = float(np.linalg.norm(b - a)) + opts.switch_tolerance
            smp = _sample_segment(ev, a, b, R, opts)
            smp["d"] = R
            if "M" in smp:
                if len(smp["M"]) == 0:
                    smp.update(rho0=float("inf"), k0=1.0, kg=None)
                else:
                    ku = _k_upper_M(smp["M"])
                    rho0, k0, kg, idx = _scan_M(smp["M"], ku=ku)
                    smp.update(rho0=float("inf") if smp["singular"] else rho0, k0=k0, kg=kg, prune=idx, ku=ku)
            elif len(smp["mu"]) == 0:
                smp.update(rho0=float("inf"), k0=1.0, kg=None, vals=None)
            else:
                rho0, k0, kg, vals = _scan(smp["mu"], smp["nu"])
                if smp["singular"]:
                    rho0 = float("inf")
                smp.update(rho0=rho0, k0=k0, kg=kg)
            cache[key] = smp
        return cache[key]

    def split(piece):
        a, b, e, d = piece
        m = 0.5 * (a + b)
        return [(a, m, e, d + 1), (m, b, e, d + 1)]

    def can_split(piece):
        a, b, _, d = piece
        return d < opts.max_depth and np.linalg.norm(b - a) / 2 >= opts.min_segment

    def ball_blocked(piece):
        """The piece's ball is not clear of the anatomy, but halving it can make its parts' balls clear."""
        if anatomy is None or not can_split(piece):
            return False
        a, b = piece[0], piece[1]
        R = float(np.linalg.norm(b - a)) + opts.switch_tolerance
        if ball_clearance(anatomy, b, R) >= anatomy.required:
            return False
        # every part of a motion keeps the motion's clearance, so a part of length l has a clear ball when
        # that clearance is >= required + l + switch_tolerance: halve while either half can get there
        # (above the floor length); this also isolates the stretches no halving can certify
        m = 0.5 * (a + b)
        reach = anatomy.motion(np.stack([a, m]), np.stack([m, b])) - opts.switch_tolerance - opts.min_segment
        return bool(np.any(reach >= anatomy.required))

    # 1) halve where the ball is not clear of the anatomy (no gain samples needed), then where the
    #    optimiser's own sample shows no certifying gain
    changed = True
    while changed:
        changed = False
        out = []
        for p in pieces:
            if ball_blocked(p):
                out += split(p)
                changed = True
            else:
                out.append(p)
        pieces = out
    changed = True
    while changed:
        changed = False
        out = []
        for p in pieces:
            smp = sample(p[0], p[1])
            if smp["rho0"] > 1.0 - opts.margin and can_split(p):
                out += split(p)
                changed = True
            else:
                out.append(p)
        pieces = out
    info: dict = {}
    segs: list[Segment] = []
    for rnd in range(opts.rounds):
        smps = [sample(p[0], p[1]) for p in pieces]
        fixed = [not (s["rho0"] <= 1.0 - opts.margin) for s in smps]
        probs = []
        Ms = []
        for i, s in enumerate(smps):
            Ms.append(None)
            if s["kg"] is None:
                probs.append({"mu": np.zeros(0, complex), "nu": np.zeros(0, complex), "d": s["d"],
                              "tol": opts.switch_tolerance, "k0": 1.0, "rho0": 1.0})
                fixed[i] = True
                continue
            prob = {"d": s["d"], "k0": s["k0"], "rho0": min(s["rho0"], 10.0),
                    "tol": opts.tolerance if i == len(smps) - 1 else opts.switch_tolerance}
            if "M" in s:  # 3-D: the pruned maps and their first cuts
                M = s["M"][s["prune"]]
                Ms[-1] = M
                prob.update(rows=_initial_cuts(M, s["k0"], s["ku"]), ku=s["ku"])
            else:
                idx = _prune(s["mu"], s["nu"], s["kg"])
                prob.update(mu=s["mu"][idx], nu=s["nu"][idx])
            probs.append(prob)
        if dim == 3:
            ks, info = _solve_with_cuts(probs, Ms, opts, fixed)
        else:
            ks, info = solve_gains(probs, opts, fixed=fixed)
        info["round"] = rnd + 1
        segs = []
        redo = []
        # every certificate of the round verified at once (the kernels see all the segments' pairs together)
        vs = verify_segments(ev, [(p[0], p[1], float(kk), s["d"]) for p, s, kk in zip(pieces, smps, ks)], opts)
        for i, (p, s, kk, v) in enumerate(zip(pieces, smps, ks, vs)):
            if progress:
                progress((rnd + (i + 1) / len(pieces)) / opts.rounds, "verifying certificates")
            a, b, e, d = p
            pred = float(_rho(s, kk)[0]) if len(s["M"] if "M" in s else s["mu"]) else float("nan")
            if s["singular"]:
                pred = float("inf")
            gn, sr = v["G_norm"], v["step_ratio"]
            if gn < 1.0 and not sr < 1.0 and not can_split(p):
                # ||G|| certifies but a large nonlinear step does not: try smaller gains.
                low = _lower_gain(ev, a, b, float(kk), s["d"], opts)
                if low is not None:
                    kk, v = low
                    gn, sr = v["G_norm"], v["step_ratio"]
                    pred = float(_rho(s, kk)[0])
            cert = bool(gn < 1.0 and sr < 1.0)  # NaN compares False: never certified by default
            reason = ""
            ball_cl = None
            if anatomy is not None:
                # the whole convergence ball must be robustly clear (docs/physics.md "Anatomy"): the
                # clearance at its centre less its radius bounds every tip of it (1-Lipschitz)
                ball_cl = ball_clearance(anatomy, b, s["d"])
                if cert and ball_cl < anatomy.required:
                    cert = False
                    reason = (f"the convergence ball (radius {s['d'] * 1000:.1f} mm) is not robustly clear of the "
                              f"anatomy: clearance >= {max(ball_cl, 0.0) * 1000:.1f} mm < {anatomy.required * 1000:.1f} mm")
                    if ball_blocked(p):
                        redo.append(i)
                    elif not can_split(p):
                        reason += " (at the floor length: no shorter segment)"
                    else:
                        own = float(anatomy.motion(a, b))
                        reason += (f" (the path keeps {own * 1000:.1f} mm here, less than the clearance + switch "
                                   f"tolerance + {opts.min_segment * 1000:.1f} mm: no shorter segment can be clear)")
            if not cert and not reason:
                if math.isnan(gn):
                    reason = "no tip of the ball is reachable under the error set"
                elif v["singular_pairs"] or s["singular"]:
                    reason = "the controller's Jacobian is singular inside the ball"
                elif not gn < 1.0:
                    reason = f"no gain found with worst-case ||G|| < 1 over the ball (best {gn:.3f})"
                elif math.isinf(sr):
                    reason = (f"||G|| = {gn:.3f} < 1, but from some tip of the ball a full step leaves the joint "
                              f"limits or pulls the shaft out of the port (the ball reaches the workspace edge)")
                else:
                    reason = f"||G|| = {gn:.3f} < 1, but a full nonlinear step grows the error (ratio {sr:.3f})"
                if can_split(p):
                    redo.append(i)
            smpinfo = {"optimiser": {k_: s[k_] for k_ in ("tips", "instances", "noise_corners", "pairs")},
                       "verification": {k_: v[k_] for k_ in ("tips", "instances", "noise_corners", "pairs", "grid_G_norm",
                                                              "reachable_tip_share", "worst_tip", "worst_theta")}}
            segs.append(Segment(a.copy(), b.copy(), float(kk), gn, sr, cert, s["d"], pred, e, d, smpinfo, reason,
                                ball_cl))
        if not redo:
            break
        pieces = [q for i, p in enumerate(pieces) for q in (split(p) if i in redo else [p])]
    return GainSchedule(path, segs, opts, info)


def single_segment(src, start, goal, options: GainOptions | None = None) -> GainSchedule:
    """The direct path as ONE segment with its best gain (no cutting, no halving), verified."""
    opts = options or _default_options(src)
    opts = GainOptions(**{**opts.__dict__, "max_segment": 1e9, "max_depth": 0, "rounds": 1}).validate()
    return schedule_gains(src, np.array([start, goal], float), opts)
