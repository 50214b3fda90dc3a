"""The gains of all segments as one casadi/IPOPT problem (the package docstring states it), with cutting
planes for 3-D segments. The only module of errplan that imports casadi.

The problem is solved over the *active rows* only: the sampled pairs (or cuts) that come within
:data:`_BAND` of a segment's worst case near its expected gain. The rows left out are checked at the
solution; any that the solution does not satisfy with room to spare joins the active rows and the
problem is solved again. The problem is convex in ``(k, r)``, so a solution of the smaller problem that
satisfies every left-out row is the solution of the whole problem (those rows' multipliers are zero);
IPOPT's iterates only see far fewer constraints. In 3-D (``|nu| = 0``) the rows' ``r - k |nu| >= 0``
is the bound ``r >= 0`` and is not repeated per row."""
from __future__ import annotations

import math
import time

import numpy as np

from .certificate import _k_upper
from .options import GainOptions
from .physics import cut_rows, gnorm3_grid

# a row is active when it comes within _BAND of its segment's worst case at a gain near the expected one
_BAND = 1e-3
# a left-out row joins when it exceeds r_s - _ROOM at the solution (it could then be active or violated)
_ROOM = 1e-6
_OPTS = {"ipopt.print_level": 0, "print_time": 0, "ipopt.sb": "yes", "ipopt.tol": 1e-10, "ipopt.max_iter": 500}


def _rows(smp: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
    """A segment's rows ``(A, B, C, ku)``: ``||G(k)||`` of row i is ``hypot(1 - k A_i, k B_i) + k C_i``
    (``C`` None in 3-D, where ``|nu| = 0``)."""
    if "rows" in smp:
        rows = np.asarray(smp["rows"], float).reshape(-1, 2)
        return rows[:, 0], rows[:, 1], None, float(smp["ku"])
    mu, nu = smp["mu"], smp["nu"]
    return mu.real, mu.imag, np.abs(nu), _k_upper(mu)


def _row_values(A: np.ndarray, B: np.ndarray, C: np.ndarray | None, k) -> np.ndarray:
    """Row values at the gains ``k`` (numpy): shape ``k.shape + (n,)``."""
    k = np.asarray(k, float)[..., None]
    v = np.sqrt((1 - k * A) ** 2 + (k * B) ** 2)
    return v if C is None else v + k * C


def _first_active(A, B, C, k0: float, ku: float, fixed: bool) -> np.ndarray:
    """Rows within :data:`_BAND` of the worst case at a gain near ``k0`` (``k0`` only when fixed)."""
    if not len(A):
        return np.zeros(0, int)
    ks = np.array([k0]) if fixed else np.clip(k0 * np.linspace(0.8, 1.25, 10), 1e-6, ku)
    v = _row_values(A, B, C, ks)
    return np.flatnonzero((v >= v.max(axis=1, keepdims=True) - _BAND).any(axis=0))


def solve_gains(samples: list[dict], opts: GainOptions, *, fixed: list[bool] | None = None) -> tuple[np.ndarray, dict]:
    """Choose every segment's gain in one casadi/IPOPT problem (see the module docstring).

    ``samples[s]`` holds the segment's pruned ``mu``/``nu`` (complex) or, in 3-D, its cut ``rows``
    (p, 2) and gain bound ``ku``, and ``d`` (ball radius),
    ``tol`` (its convergence tolerance), ``k0``/``rho0`` (numpy scan); ``fixed[s]`` marks a
    segment no gain certifies: its gain stays at the scan's best and it does not constrain the
    others beyond the (soft) gain-change bound. Returns the gains and a solver report.
    """
    return _solve(samples, opts, fixed or [False] * len(samples))[:2]


def _solve(samples: list[dict], opts: GainOptions, fixed: list[bool],
           active: list[np.ndarray] | None = None) -> tuple[np.ndarray, dict, list[np.ndarray]]:
    """:func:`solve_gains` from the active rows ``active[s]`` (indices; :func:`_first_active` when
    None), adding left-out rows until the solution satisfies them all (should IPOPT fail on the active
    rows, the whole problem is solved instead). Returns the active rows too."""
    data = [_rows(smp) for smp in samples]
    if active is None:
        active = [_first_active(A, B, C, smp["k0"], ku, fx) for (A, B, C, ku), smp, fx in zip(data, samples, fixed)]
    active = [np.asarray(a, int) for a in active]
    S = len(samples)
    t0 = time.perf_counter()
    solves = iterations = 0
    while True:
        xs, f, stats = _ipopt(samples, data, active, opts, fixed)
        solves += 1
        iterations += int(stats.get("iter_count", -1))
        ok = bool(stats.get("success", False)) and bool(np.all(np.isfinite(xs)))
        if not ok:
            if all(len(a) == len(d[0]) for a, d in zip(active, data)):
                break
            active = [np.arange(len(d[0])) for d in data]  # once more with every row, as the whole problem
            continue
        grew = False
        for s, (A, B, C, ku) in enumerate(data):
            if len(active[s]) == len(A):
                continue
            v = _row_values(A, B, C, xs[s])
            out = np.ones(len(A), bool)
            out[active[s]] = False
            join = out & (v > xs[S + s] - _ROOM)
            if join.any():
                # the violated rows and, with them, every left-out row near the worst case at this gain
                join |= out & (v >= v.max() - _BAND)
                active[s] = np.union1d(active[s], np.flatnonzero(join))
                grew = True
        if not grew:
            break
    ks = xs[:S]
    info = {"solver": "ipopt", "status": stats.get("return_status", "?"), "success": ok,
            "iterations": iterations, "objective": f, "time_s": time.perf_counter() - t0, "segments": S,
            "constraints": int(sum(len(d[0]) for d in data)), "active_rows": int(sum(len(a) for a in active)),
            "solves": solves, "gain_change_slack": float(xs[2 * S:].max()) if S > 1 else 0.0}
    if not ok:
        # Fall back to each segment's own best gain: still verified below, never assumed.
        ks = np.array([s["k0"] for s in samples])
        info["fallback"] = "per-segment scan gains (the joint problem did not solve)"
    return ks, info, active


def _ipopt(samples: list[dict], data: list[tuple], active: list[np.ndarray], opts: GainOptions,
           fixed: list[bool]) -> tuple[np.ndarray, float, dict]:
    """One IPOPT solve over the active rows: the solution ``(k, r, sigma)``, objective and stats."""
    import casadi as ca

    S = len(samples)
    k = ca.SX.sym("k", S)
    r = ca.SX.sym("r", S)
    sig = ca.SX.sym("sigma", max(S - 1, 0))
    # every active row at once: its segment, (A, B) and, in the plane, C = |nu|
    seg = np.concatenate([np.full(len(a), s, int) for s, a in enumerate(active)] + [np.zeros(0, int)])
    A = np.concatenate([d[0][a] for d, a in zip(data, active)] + [np.zeros(0)])
    B = np.concatenate([d[1][a] for d, a in zip(data, active)] + [np.zeros(0)])
    planar = np.concatenate([np.full(len(a), d[2] is not None) for d, a in zip(data, active)] + [np.zeros(0, bool)])
    C = np.concatenate([d[2][a] if d[2] is not None else np.zeros(len(a)) for d, a in zip(data, active)]
                       + [np.zeros(0)])
    g = []
    if len(seg):
        kr, rr = ca.vec(k[seg.tolist()]), ca.vec(r[seg.tolist()])  # (rows, 1)
        slackr = rr - kr * ca.DM(C) if planar.any() else rr  # in 3-D r - k |nu| = r >= 0 is r's bound
        g.append(slackr ** 2 - (1 - kr * ca.DM(A)) ** 2 - (kr * ca.DM(B)) ** 2)
        if planar.any():
            g.append(ca.vec(slackr[np.flatnonzero(planar).tolist()]))
    fx = np.asarray(fixed, bool)
    k0 = np.array([smp["k0"] for smp in samples], float)
    rho0 = np.array([smp["rho0"] for smp in samples], float)
    ku = np.array([d[3] for d in data], float)
    free = np.flatnonzero(~fx).tolist()
    w = [max(math.log(samples[s]["d"] / samples[s]["tol"]), 1e-3) for s in free]
    obj = ca.dot(ca.DM(w), 1 / (-ca.log(ca.vec(r[free])))) + 1e-3 * ca.sum1(ca.vec(r[np.flatnonzero(fx).tolist()]))
    if S > 1:
        dk = k[1:] - k[:-1]
        g.append(ca.vec(ca.horzcat(dk - sig, -dk - sig).T))  # (dk_s - sigma_s, -dk_s - sigma_s) per s
        obj += opts.slack_weight * ca.sum1(sig)
    n_rows = len(seg) + int(planar.sum())
    lbg = np.concatenate([np.zeros(n_rows), np.full(2 * (S - 1), -np.inf)])
    ubg = np.concatenate([np.full(n_rows, np.inf), np.full(2 * (S - 1), opts.max_gain_change)])
    lbx = np.concatenate([np.where(fx, k0, 1e-6), np.where(fx, 0.0, 1e-6), np.zeros(S - 1)])
    ubx = np.concatenate([np.where(fx, k0, ku), np.where(fx, np.inf, 1.0 - opts.margin), np.full(S - 1, np.inf)])
    x0 = np.concatenate([k0, np.where(fx, rho0, np.minimum(rho0 + 1e-9, 1.0 - opts.margin)),
                         np.maximum(np.abs(np.diff(k0)) - opts.max_gain_change, 0.0)])
    nlp = {"x": ca.vertcat(k, r, sig), "f": obj, "g": ca.vertcat(*g) if g else ca.SX(0, 1)}
    solver = ca.nlpsol("gains", "ipopt", nlp, _OPTS)
    sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    return np.asarray(sol["x"]).ravel(), float(sol["f"]), solver.stats()


def _initial_cuts(M: np.ndarray, k0: float, ku: float) -> np.ndarray:
    """Cut rows of the pruned pairs at the scan's gain and at 0.8 and 1.25 times it (within ``ku``);
    the cutting-plane loop adds what the solution needs."""
    ks = [k0] + [min(f * k0, ku) for f in (0.8, 1.25)]
    return np.vstack([cut_rows(M, kk) for kk in ks])


def _solve_with_cuts(probs: list[dict], Ms: list, opts: GainOptions, fixed: list[bool],
                     max_rounds: int = 12) -> tuple[np.ndarray, dict]:
    """:func:`solve_gains` with cutting planes for the 3-D segments (``Ms[s]`` their pruned maps,
    None for planar ones): after each solve, add the singular-vector cut at the solved gain for
    every pair whose exact ``||I - k M||`` exceeds the cuts by more than 1e-9; stop when none does.
    Each round starts from the previous round's active rows and the new cuts."""
    total = solves = 0
    active = None
    for it in range(max_rounds):
        ks, info, active = _solve(probs, opts, fixed, active)
        solves += info["solves"]
        added = 0
        for s, (pr, M) in enumerate(zip(probs, Ms)):
            if M is None or not len(M) or fixed[s]:
                continue
            kk = float(ks[s])
            exact = gnorm3_grid(M, kk)[0]
            rows = pr["rows"]
            cuts = np.sqrt((1 - kk * rows[:, 0]) ** 2 + (kk * rows[:, 1]) ** 2).max()
            gap = exact.max() - cuts
            if gap > 1e-9:
                hot = exact > cuts + 1e-9
                pr["rows"] = np.vstack([rows, cut_rows(M[hot], kk)])
                active[s] = np.concatenate([active[s], len(rows) + np.arange(int(hot.sum()))])
                added += int(hot.sum())
        total += added
        if not added:
            break
    info["cut_rounds"] = it + 1
    info["cuts_added"] = total
    info["solves"] = solves
    return ks, info
