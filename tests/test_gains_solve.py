"""The gain problem over its active rows (errplan.gains.solve) against the whole problem: the reference
below is the formulation with every sampled pair (or cut) as two constraints per row, kept here as it
was before the active rows. Seeded random planar and 3-D problems shaped like the schedule's (several
segments, some fixed, pruned pairs, first cuts at the scan's gain), the growth of the active rows from a
deliberately poor start, and whole schedules on bundled scenarios with either solver."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import errplan.gains.schedule as schedule_mod
from errplan.api import load_scenario
from errplan.gains import GainOptions, SpatialModel, gnorm3_grid, options_from_scenario, rho_of_k, schedule_gains
from errplan.gains import solve as solve_mod
from errplan.gains.certificate import _k_upper, _k_upper_M, _scan_M
from errplan.gains.physics import cut_rows
from errplan.gains.solve import _initial_cuts, _solve, _solve_with_cuts, solve_gains

ROOT = Path(__file__).resolve().parents[1]
BOUNDED = ROOT / "scenarios" / "beasley2004_bounded.toml"
PHANTOM = ROOT / "scenarios" / "phantom15_spatial.toml"


# ---- the reference: every row in the problem, one casadi expression per segment --------------------------

def _ref_solve_gains(samples, opts, *, fixed=None):
    S = len(samples)
    fixed = fixed or [False] * S
    k = ca.SX.sym("k", S)
    r = ca.SX.sym("r", S)
    sig = ca.SX.sym("sigma", max(S - 1, 0))
    g, lbg, ubg = [], [], []
    obj = 0
    lbx_k, ubx_k, lbx_r, ubx_r, x0_k, x0_r = [], [], [], [], [], []
    for s, smp in enumerate(samples):
        if "rows" in smp:
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
    sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    stats = solver.stats()
    ks = np.asarray(sol["x"]).ravel()[:S]
    info = {"success": bool(stats.get("success", False)), "objective": float(sol["f"])}
    if not info["success"] or not np.all(np.isfinite(ks)):
        ks = np.array([s["k0"] for s in samples])
        info["fallback"] = "per-segment scan gains (the joint problem did not solve)"
    return ks, info


def _ref_solve_with_cuts(probs, Ms, opts, fixed, max_rounds=12):
    total = 0
    for it in range(max_rounds):
        ks, info = _ref_solve_gains(probs, opts, fixed=fixed)
        added = 0
        for s, (pr, M) in enumerate(zip(probs, Ms)):
            if M is None or not len(M) or fixed[s]:
                continue
            kk = float(ks[s])
            exact = gnorm3_grid(M, kk)[0]
            rows = pr["rows"]
            cuts = np.sqrt((1 - kk * rows[:, 0]) ** 2 + (kk * rows[:, 1]) ** 2).max()
            if exact.max() - cuts > 1e-9:
                hot = exact > cuts + 1e-9
                pr["rows"] = np.vstack([rows, cut_rows(M[hot], kk)])
                added += int(hot.sum())
        total += added
        if not added:
            break
    info["cut_rounds"] = it + 1
    return ks, info


# ---- seeded problems shaped like the schedule's -----------------------------------------------------------

def _planar_problem(seed: int, S: int = 5, n: int = 60):
    """S segments of n pairs: mu around a segment's own centre, |nu| small; the last segment's worst case
    is pushed above 1 - margin (fixed, as the schedule marks it)."""
    rng = np.random.default_rng(seed)
    opts = GainOptions()
    probs, fixed = [], []
    for s in range(S):
        c = rng.uniform(0.8, 1.3)
        spread = 2.0 if s == S - 1 else rng.uniform(0.15, 0.4)
        mu = c + spread * (rng.uniform(-1, 1, n) + 0.5j * rng.uniform(-1, 1, n))
        nu = rng.uniform(0, 0.1, n) * np.exp(2j * np.pi * rng.uniform(size=n))
        kg = np.linspace(_k_upper(mu) / 801, _k_upper(mu), 801)
        vals = rho_of_k(mu, nu, kg)
        j = int(np.argmin(vals))
        probs.append({"mu": mu, "nu": nu, "d": rng.uniform(0.005, 0.02),
                      "tol": opts.tolerance if s == S - 1 else opts.switch_tolerance,
                      "k0": float(kg[j]), "rho0": float(vals[j])})
        fixed.append(not vals[j] <= 1.0 - opts.margin)
    return probs, opts, fixed


def _spatial_problem(seed: int, S: int = 5, n: int = 400):
    """S segments of n maps M = I + noise (one segment with large noise, fixed), pruned on the compiled
    k-grid and given their first cuts, as the schedule does."""
    rng = np.random.default_rng(seed)
    opts = GainOptions.for_dim(3)
    probs, Ms, fixed = [], [], []
    for s in range(S):
        scale = 0.9 if s == 2 else rng.uniform(0.1, 0.3)
        M = np.eye(3) * rng.uniform(0.8, 1.2) + scale * rng.normal(size=(n, 3, 3))
        rho0, k0, kg, idx = _scan_M(M)
        ku = _k_upper_M(M)
        Mp = M[idx]
        fx = not rho0 <= 1.0 - opts.margin
        probs.append({"rows": _initial_cuts(Mp, k0, ku), "ku": ku, "d": rng.uniform(0.005, 0.02),
                      "tol": opts.switch_tolerance, "k0": k0, "rho0": min(rho0, 10.0)})
        Ms.append(Mp)
        fixed.append(fx)
    return probs, Ms, opts, fixed


def _row_max(smp, k):
    if "rows" in smp:
        rows = smp["rows"]
        return float(np.sqrt((1 - k * rows[:, 0]) ** 2 + (k * rows[:, 1]) ** 2).max())
    return float(rho_of_k(smp["mu"], smp["nu"], k)[0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planar_gains_match_whole_problem(seed):
    probs, opts, fixed = _planar_problem(seed)
    assert any(fixed) and not all(fixed)
    # a segment without a reachable pair, as the schedule gives it (fixed, no rows)
    probs.insert(2, {"mu": np.zeros(0, complex), "nu": np.zeros(0, complex), "d": 0.01,
                     "tol": opts.switch_tolerance, "k0": 1.0, "rho0": 1.0})
    fixed.insert(2, True)
    ks_ref, info_ref = _ref_solve_gains(copy.deepcopy(probs), opts, fixed=fixed)
    ks, info = solve_gains(copy.deepcopy(probs), opts, fixed=fixed)
    assert info_ref["success"] and info["success"], (info_ref, info)
    assert info["active_rows"] < info["constraints"]  # the active rows are a real subset here
    assert np.abs(ks - ks_ref).max() < 1e-7
    assert abs(info["objective"] - info_ref["objective"]) < 1e-7 * max(1.0, abs(info_ref["objective"]))
    # every row (active or not) holds at the solution: the worst case stays within 1 - margin
    for s, smp in enumerate(probs):
        if not fixed[s]:
            assert _row_max(smp, ks[s]) <= 1.0 - opts.margin + 1e-8


@pytest.mark.parametrize("seed", [3, 4])
def test_spatial_cutting_planes_match_whole_problem(seed):
    probs, Ms, opts, fixed = _spatial_problem(seed)
    assert any(fixed) and not all(fixed)
    ref_probs, new_probs = copy.deepcopy(probs), copy.deepcopy(probs)
    ks_ref, info_ref = _ref_solve_with_cuts(ref_probs, Ms, opts, fixed)
    ks, info = _solve_with_cuts(new_probs, Ms, opts, fixed)
    assert info_ref["success"] and info["success"], (info_ref, info)
    assert np.abs(ks - ks_ref).max() < 1e-7
    for s, M in enumerate(Ms):
        if fixed[s]:
            assert ks[s] == probs[s]["k0"]
            continue
        # the exact sigma_max over the pruned maps (SVD, numpy) agrees with the cuts and certifies
        exact = np.linalg.norm(np.eye(3) - ks[s] * M, ord=2, axis=(-2, -1)).max()
        assert exact <= _row_max(new_probs[s], ks[s]) + 1e-8
        assert exact <= 1.0 - opts.margin + 1e-8


@pytest.mark.parametrize("kind", ["planar", "spatial"])
def test_active_rows_grow_from_a_poor_start(kind):
    """One row per segment to start with (the least binding one): the left-out rows are violated at the
    first solution, join, and the solves end on the whole problem's solution."""
    if kind == "planar":
        probs, opts, fixed = _planar_problem(5, S=4, n=80)
    else:
        probs, _, opts, fixed = _spatial_problem(6, S=3, n=200)
    data = [solve_mod._rows(p) for p in probs]
    start = [np.array([int(np.argmin(solve_mod._row_values(A, B, C, p["k0"])))])
             for (A, B, C, _), p in zip(data, probs)]
    ks, info, active = _solve(copy.deepcopy(probs), opts, list(fixed), start)
    ks_ref, info_ref = _ref_solve_gains(copy.deepcopy(probs), opts, fixed=fixed)
    assert info["success"] and info["solves"] >= 2
    assert all(len(a) > 1 for a in active)
    assert np.abs(ks - ks_ref).max() < 1e-7


def test_fallback_when_ipopt_fails(monkeypatch):
    """A failed solve on the active rows is retried with every row; failing that too, every segment
    gets its scan gain, as before (and says so)."""
    probs, opts, fixed = _planar_problem(7, S=3, n=40)
    monkeypatch.setitem(solve_mod._OPTS, "ipopt.max_iter", 1)
    ks, info = solve_gains(probs, opts, fixed=fixed)
    assert not info["success"] and "fallback" in info
    assert info["solves"] == 2 and info["active_rows"] == info["constraints"]
    assert np.array_equal(ks, [p["k0"] for p in probs])


def _with_reference(monkeypatch):
    monkeypatch.setattr(schedule_mod, "solve_gains", _ref_solve_gains)
    monkeypatch.setattr(schedule_mod, "_solve_with_cuts", _ref_solve_with_cuts)


def _compare_schedules(new, ref):
    assert len(new.segments) == len(ref.segments)
    for a, b in zip(new.segments, ref.segments):
        assert abs(a.gain - b.gain) < 1e-7
        assert a.certified == b.certified
        assert abs(a.certified_G_norm - b.certified_G_norm) < 1e-6
    assert new.certified == ref.certified


def test_planar_schedule_same_as_whole_problem(monkeypatch):
    sc = load_scenario(BOUNDED)
    path = np.array([[-0.1, 0.40], [0.0, 0.385], [0.1, 0.40]])
    new = schedule_gains(sc, path)
    _with_reference(monkeypatch)
    ref = schedule_gains(sc, path)
    assert new.certified
    _compare_schedules(new, ref)


def test_spatial_schedule_same_as_whole_problem(monkeypatch):
    sc = load_scenario(PHANTOM)
    model = SpatialModel(sc)
    opts = options_from_scenario(sc)
    path = np.array([[-0.06, 0.03, 0.36], [-0.03, 0.04, 0.375], [0.0, 0.03, 0.38]])
    new = schedule_gains(model, path, opts)
    _with_reference(monkeypatch)
    ref = schedule_gains(model, path, opts)
    assert any(s.certified for s in new.segments)
    _compare_schedules(new, ref)
