"""The gains of all segments as one casadi/IPOPT problem (the package docstring states it), with cutting
planes for 3-D segments. The only module of errplan that imports casadi."""
from __future__ import annotations

import math
import time

import numpy as np

from .certificate import _k_upper
from .options import GainOptions
from .physics import cut_rows, gnorm3_grid


def solve_gains(samples: list[dict], opts: GainOptions, *, fixed: list[bool] | None = None) -> tuple[np.ndarray, dict]:
    """Choose every segment's gain in one casadi/IPOPT problem (see the module docstring).

    ``samples[s]`` holds the segment's pruned ``mu``/``nu`` (complex) or, in 3-D, its cut ``rows``
    (p, 2) and gain bound ``ku``, and ``d`` (ball radius),
    ``tol`` (its convergence tolerance), ``k0``/``rho0`` (numpy scan); ``fixed[s]`` marks a
    segment no gain certifies: its gain stays at the scan's best and it does not constrain the
    others beyond the (soft) gain-change bound. Returns the gains and a solver report.
    """
    import casadi as ca

    S = len(samples)
    fixed = fixed or [False] * S
    k = ca.SX.sym("k", S)
    r = ca.SX.sym("r", S)
    sig = ca.SX.sym("sigma", max(S - 1, 0))
    g, lbg, ubg = [], [], []
    obj = 0
    lbx_k, ubx_k, lbx_r, ubx_r, x0_k, x0_r = [], [], [], [], [], []
    for s, smp in enumerate(samples):
        if "rows" in smp:  # 3-D cuts (a, b): ||(I - kM) v|| = sqrt((1 - k a)^2 + (k b)^2), |nu| = 0
            rows = smp["rows"]
            A, B, C = ca.DM(rows[:, 0]), ca.DM(rows[:, 1]), ca.DM(np.zeros(len(rows)))
            n = len(rows)
            ku = smp["ku"]
        else:
            mu, nu = smp["mu"], smp["nu"]
            A, B, C = ca.DM(mu.real), ca.DM(mu.imag), ca.DM(np.abs(nu))
            n = len(mu)
            ku = _k_upper(mu)
        slackr = r[s] - k[s] * C
        g += [slackr ** 2 - (1 - k[s] * A) ** 2 - (k[s] * B) ** 2, slackr]
        lbg += [0.0] * (2 * n)
        ubg += [ca.inf] * (2 * n)
        if fixed[s]:
            lbx_k.append(smp["k0"]); ubx_k.append(smp["k0"])
            lbx_r.append(0.0); ubx_r.append(ca.inf)
            obj += 1e-3 * r[s]
        else:
            lbx_k.append(1e-6); ubx_k.append(ku)
            lbx_r.append(1e-6); ubx_r.append(1.0 - opts.margin)
            obj += max(math.log(smp["d"] / smp["tol"]), 1e-3) / (-ca.log(r[s]))
        x0_k.append(smp["k0"])
        x0_r.append(min(smp["rho0"] + 1e-9, 1.0 - opts.margin) if not fixed[s] else smp["rho0"])
    for s in range(S - 1):
        dk = k[s + 1] - k[s]
        g += [dk - sig[s], -dk - sig[s]]
        lbg += [-ca.inf, -ca.inf]
        ubg += [opts.max_gain_change, opts.max_gain_change]
        obj += opts.slack_weight * sig[s]
    x = ca.vertcat(k, r, sig)
    lbx = lbx_k + lbx_r + [0.0] * (S - 1)
    ubx = ubx_k + ubx_r + [ca.inf] * (S - 1)
    x0 = x0_k + x0_r + [max(abs(x0_k[s + 1] - x0_k[s]) - opts.max_gain_change, 0.0) for s in range(S - 1)]
    nlp = {"x": x, "f": obj, "g": ca.vertcat(*[ca.vec(e) for e in g])}
    solver = ca.nlpsol("gains", "ipopt", nlp, {"ipopt.print_level": 0, "print_time": 0, "ipopt.sb": "yes",
                                                "ipopt.tol": 1e-10, "ipopt.max_iter": 500})
    t0 = time.perf_counter()
    sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    stats = solver.stats()
    xs = np.asarray(sol["x"]).ravel()
    ks = xs[:S]
    info = {"solver": "ipopt", "status": stats.get("return_status", "?"), "success": bool(stats.get("success", False)),
            "iterations": int(stats.get("iter_count", -1)), "objective": float(sol["f"]),
            "time_s": time.perf_counter() - t0, "segments": S,
            "constraints": int(sum(len(s["rows"]) if "rows" in s else len(s["mu"]) for s in samples)),
            "gain_change_slack": float(xs[2 * S:].max()) if S > 1 else 0.0}
    if not info["success"] or not np.all(np.isfinite(ks)):
        # Fall back to each segment's own best gain: still verified below, never assumed.
        ks = np.array([s["k0"] for s in samples])
        info["fallback"] = "per-segment scan gains (the joint problem did not solve)"
    return ks, info


def _initial_cuts(M: np.ndarray, k0: float, ku: float) -> np.ndarray:
    """Cut rows of the pruned pairs at the scan's gain and at 0.8 and 1.25 times it (within ``ku``);
    the cutting-plane loop adds what the solution needs."""
    ks = [k0] + [min(f * k0, ku) for f in (0.8, 1.25)]
    return np.vstack([cut_rows(M, kk) for kk in ks])


def _solve_with_cuts(probs: list[dict], Ms: list, opts: GainOptions, fixed: list[bool],
                     max_rounds: int = 12) -> tuple[np.ndarray, dict]:
    """:func:`solve_gains` with cutting planes for the 3-D segments (``Ms[s]`` their pruned maps,
    None for planar ones): after each solve, add the singular-vector cut at the solved gain for
    every pair whose exact ``||I - k M||`` exceeds the cuts by more than 1e-9; stop when none does."""
    total = 0
    for it in range(max_rounds):
        ks, info = solve_gains(probs, opts, fixed=fixed)
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
                added += int(hot.sum())
        total += added
        if not added:
            break
    info["cut_rounds"] = it + 1
    info["cuts_added"] = total
    return ks, info
