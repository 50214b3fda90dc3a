"""Worst-case fields (errplan.fields) against an independent implementation of docs/physics.md.

The independent implementation below shares no code with errplan: its own arm forward model and
brute-force IK (a joint grid, nearest neighbours, Newton), its own P2 beam (eq. 18 solved by
bisection, the inverse by bisection on the tip side, checked by the forward model), Jacobians by
central differences of its own forward models (including the arm: J = J_tw J_arm), numpy's inv
and SVD for ||G||, a dense direction search for |phi_max|, and a dense grid over the error box
(21 x 21 port offsets, 7 tip loads). It reads the scenario document (a dict), not errplan's
Scenario. Then: refinement stability, robust validity, the npz contract, rho* and k*.
"""
from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from conftest import SCENARIOS, make_scenario_dict
from errplan.errors import ErrplanError
from errplan.fields import REFINE_LEVELS, Evaluator, MetricField, compute_fields, minimize_gain, worst_case
from errplan.metrics import g_norm_from_parts
from errplan.scenario import Uncertainty
from errplan.api import load_scenario, parse_scenario
from errplan.models import build_arm

TOL_G = 1e-3      # ||G||: absolute, relative above 1 (near singular tips ||G|| reaches 1e4)
TOL_PHI = 3e-3    # |phi_max|, rad


# ============================================================================ independent model
class Robot:
    def __init__(self, doc):
        r = doc["robot"]
        self.base = np.asarray(r["base"], float)
        self.l1, self.l2 = r["link_lengths"]
        self.h1, self.h2 = r["home_angles"]
        (self.lo1, self.hi1), (self.lo2, self.hi2) = r["joint_limits"]
        self.slo, self.shi = r["joint_sum_limits"]
        q1 = np.linspace(self.lo1, self.hi1, 241)
        q2 = np.linspace(self.lo2, self.hi2, 241)
        Q = np.stack(np.meshgrid(q1, q2, indexing="ij"), -1).reshape(-1, 2)
        self.Q = Q[(Q.sum(-1) >= self.slo) & (Q.sum(-1) <= self.shi)]
        self.tree = cKDTree(self.fk(self.Q))

    def fk(self, q):
        a1 = q[..., 0] + self.h1
        a2 = a1 + q[..., 1] + self.h2
        return np.stack([self.base[0] + self.l1 * np.sin(a1) + self.l2 * np.sin(a2),
                         self.base[1] + self.l1 * np.cos(a1) + self.l2 * np.cos(a2)], -1)

    def jac(self, q, h=1e-7):
        return np.stack([(self.fk(q + e) - self.fk(q - e)) / (2 * h) for e in (np.array([h, 0.0]), np.array([0.0, h]))], -1)

    def inside(self, q, tol=1e-9):
        s = q[..., 0] + q[..., 1]
        return ((q[..., 0] >= self.lo1 - tol) & (q[..., 0] <= self.hi1 + tol) & (q[..., 1] >= self.lo2 - tol)
                & (q[..., 1] <= self.hi2 + tol) & (s >= self.slo - tol) & (s <= self.shi + tol))

    def ik(self, w, seeds=4, iters=14):
        """Brute force: the nearest joint-grid points (in wrist space) polished by Newton; a wrist is
        reachable if some seed converges inside the limits."""
        _, idx = self.tree.query(w, k=seeds)
        q_out = np.full(w.shape, np.nan)
        ok = np.zeros(len(w), bool)
        for j in range(seeds):
            rows = np.flatnonzero(~ok)
            if len(rows) == 0:
                break
            q, ww = self.Q[idx[rows, j]].copy(), w[rows]
            for _ in range(iters):
                r = self.fk(q) - ww
                if np.max(np.abs(r)) < 1e-13:
                    break
                J = self.jac(q)
                det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
                det = np.where(np.abs(det) < 1e-12, 1e-12, det)
                step = np.stack([J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1],
                                 -J[:, 1, 0] * r[:, 0] + J[:, 0, 0] * r[:, 1]], -1) / det[:, None]
                nrm = np.linalg.norm(step, axis=-1, keepdims=True)
                q = q - np.where(nrm > 0.3, step * 0.3 / np.maximum(nrm, 1e-300), step)
            good = (np.linalg.norm(self.fk(q) - ww, axis=-1) < 1e-10) & self.inside(q)
            q_out[rows[good]] = q[good]
            ok[rows[good]] = True
        return q_out, ok


def _bisect(f, lo, hi, iters=56):
    for _ in range(iters):
        m = 0.5 * (lo + hi)
        neg = f(m) < 0
        lo, hi = np.where(neg, m, lo), np.where(neg, hi, m)
    return 0.5 * (lo + hi)


def beam_tip(w, p, L, t):
    """P2 eqs. 6, 7, 10, 18 (Fp = Ft L / a): a from |p - w|^2 = a^2 + y_m(a)^2 by bisection."""
    d = p - w
    rho = np.hypot(d[..., 0], d[..., 1])
    if np.all(t == 0):
        return w + L * d / rho[..., None]
    a = _bisect(lambda a: a * a + (t * a * (L - a) ** 2 / 3) ** 2 - rho * rho, 0 * rho, np.minimum(rho, L))
    ym = -t * a * (L - a) ** 2 / 3
    phi = np.arctan2(d[..., 0], d[..., 1]) - np.arctan(ym / a)
    return w + L * np.stack([np.sin(phi), np.cos(phi)], -1)


def beam_wrist(x, p, L, t):
    """The wrist putting the flexed tip at x: tip-side length b from |x - p|^2 = b^2 + y_m^2."""
    d = x - p
    r = np.hypot(d[..., 0], d[..., 1])
    if np.all(t == 0):
        return x - L * d / r[..., None]
    b = _bisect(lambda b: b * b + (t * (L - b) * b * b / 3) ** 2 - r * r, 0 * r, np.minimum(r, L))
    ym = -t * (L - b) * b * b / 3
    phi = np.arctan2(d[..., 0], d[..., 1]) + np.arctan2(ym, b)   # chord = angle(x - p) - angle(-y_m, b)
    return x - L * np.stack([np.sin(phi), np.cos(phi)], -1)


def fd(f, w, h=1e-6):
    """Central differences of f at wrists w (n, 2); h a scalar or per-row steps (n,)."""
    h = np.broadcast_to(np.asarray(h, float), w.shape[:-1])[..., None]
    cols = []
    for e in (np.array([1.0, 0.0]), np.array([0.0, 1.0])):
        cols.append((f(w + h * e) - f(w - h * e)) / (2 * h))
    return np.stack(cols, -1)


def fd_near(f, w, p):
    """fd with a step scaled to the distance of the wrist from the port p (the beam's curvature
    grows like 1/|p - w|^3 there): 1e-4 |p - w|, at most 1e-6."""
    return fd(f, w, 1e-4 * np.minimum(np.linalg.norm(p - w, axis=-1), 0.01))


def direction_search(M, n=90, stages=8):
    """max over unit v of |angle(v, M v)| by search: the cosine of the angle over n directions of
    [0, pi) (v and -v turn alike), then 8 stages of local refinement around the two deepest local
    minima (11 points over +-step, step / 5 each stage); the angle is arccos at the end."""
    m00, m01, m10, m11 = (M[..., i, j][..., None] for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)))

    def cosang(c, sn):
        u0 = m00 * c + m01 * sn
        u1 = m10 * c + m11 * sn
        return (c * u0 + sn * u1) / np.maximum(np.hypot(u0, u1), 1e-300)

    s = np.linspace(0, np.pi, n, endpoint=False)
    cs = cosang(np.cos(s), np.sin(s))
    lmin = (cs <= np.roll(cs, 1, -1)) & (cs <= np.roll(cs, -1, -1))
    order = np.argsort(np.where(lmin, cs, np.inf), axis=-1)[..., :2]
    best = cs.min(-1)
    d = np.linspace(-1.0, 1.0, 11)
    for i in (order[..., 0], order[..., 1]):
        c0, h = s[i][..., None], np.pi / n
        for _ in range(stages):
            cd, sd = np.cos(h * d), np.sin(h * d)
            cc, ss = np.cos(c0), np.sin(c0)
            cf = cosang(cc * cd - ss * sd, ss * cd + cc * sd)   # directions c0 + h d
            j = np.argmin(cf, -1)[..., None]
            best = np.minimum(best, np.take_along_axis(cf, j, -1)[..., 0])
            c0, h = c0 + h * d[j], h / 5
    return np.arccos(np.clip(best, -1.0, 1.0))


def instance_metrics(robot, doc, x, port, t):
    """(ok, ||G||, |phi_max|) at tips x (n, 2) with true ports port (n, 2) and one tip load t
    (rigid controller: the lever through [port] estimate)."""
    L = doc["instrument"]["length"]
    est = np.asarray(doc["port"]["estimate"], float)
    k = doc.get("controller", {}).get("gain", 1.0)
    n = len(x)
    ok = np.zeros(n, bool)
    G = np.full(n, np.nan)
    P = np.full(n, np.nan)
    r = np.linalg.norm(x - port, axis=-1)
    sel = np.flatnonzero((r < L) & (r > 1e-9))
    if len(sel) == 0:
        return ok, G, P
    p = port[sel]
    w = beam_wrist(x[sel], p, L, t)
    conv = np.linalg.norm(beam_tip(w, p, L, t) - x[sel], axis=-1) < 1e-9
    q, okq = robot.ik(w)
    okq &= conv
    sel, w, q, p = sel[okq], w[okq], q[okq], p[okq]
    Ja = robot.jac(q)
    J = fd_near(lambda ww: beam_tip(ww, p, L, t), w, p) @ Ja
    Jh_tw = fd_near(lambda ww: beam_tip(ww, est, L, 0.0), w, est)
    sing = np.abs(np.linalg.det(Jh_tw)) <= 1e-9 * np.einsum("...ij,...ij->...", Jh_tw, Jh_tw)
    Jh = Jh_tw @ Ja
    Jh[sing] = np.eye(2)
    M = J @ np.linalg.inv(Jh)
    ok[sel[~sing]] = True
    G[sel] = np.linalg.norm(np.eye(2) - k * M, 2, axis=(-2, -1))
    P[sel] = np.concatenate([direction_search(M[i:i + 20000]) for i in range(0, len(M), 20000)])
    G[sel[sing]] = np.nan
    return ok, G, P


def error_instances(doc, n_port=21, n_load=7):
    u = doc.get("uncertainty", {})
    if "port_y" in u or "port_z" in u:
        base = np.asarray(doc["port"]["estimate"], float)
    else:
        base = np.asarray(doc["port"]["position"], float)
    axes = []
    for key, n in (("port_y", n_port), ("port_z", n_port), ("tip_force_over_ei", n_load)):
        lo, hi = u.get(key, (0.0, 0.0))
        axes.append(np.linspace(lo, hi, n) if hi > lo else np.array([lo]))
    th = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return base, th


def independent_field(doc, x, n_port=21, n_load=7, rows=150_000):
    """Worst case over the sampled error box at tips x: (valid, ||G||, |phi_max|). All port
    instances of one tip load are evaluated together (tips x instances stacked)."""
    robot = Robot(doc)
    base, th = error_instances(doc, n_port, n_load)
    n = len(x)
    valid = np.ones(n, bool)
    G = np.full(n, -np.inf)
    P = np.full(n, -np.inf)
    for t in np.unique(th[:, 2]):
        ports = base + th[th[:, 2] == t][:, :2]
        step = max(1, rows // max(n, 1))
        for i in range(0, len(ports), step):
            pp = ports[i:i + step]
            idx = np.flatnonzero(valid)
            m = len(pp)
            X = np.broadcast_to(x[idx], (m, len(idx), 2)).reshape(-1, 2)
            PP = np.broadcast_to(pp[:, None, :], (m, len(idx), 2)).reshape(-1, 2)
            ok, g, p = (a.reshape(m, len(idx)) for a in instance_metrics(robot, doc, X, PP, t))
            allok = ok.all(axis=0)
            valid[idx[~allok]] = False
            G[idx] = np.maximum(G[idx], np.where(ok, g, -np.inf).max(axis=0))
            P[idx] = np.maximum(P[idx], np.where(ok, p, -np.inf).max(axis=0))
    G[~valid] = np.nan
    P[~valid] = np.nan
    return valid, G, P


def random_doc(seed: int, tip_load: bool, port_box: bool = True) -> dict:
    """A scenario errplan has never seen: arm, limits, shaft, port, estimate, box, gain, loads."""
    rng = np.random.default_rng(seed)
    l1, l2 = rng.uniform(0.15, 0.3, 2)
    base = rng.uniform(-0.1, 0.1, 2) + [0.2, -0.2]
    h1, h2 = rng.uniform(-0.3, 0.3), -np.pi / 2 + rng.uniform(-0.3, 0.3)
    lim1 = [rng.uniform(-2.0, -0.8), rng.uniform(0.6, 1.4)]
    lim2 = [rng.uniform(-0.9, -0.4), rng.uniform(0.6, 1.2)]
    L = rng.uniform(0.25, 0.4)
    q = np.array([rng.uniform(lim1[0] / 2, lim1[1] / 2), rng.uniform(lim2[0] / 2, lim2[1] / 2)])
    a1 = q[0] + h1
    a2 = a1 + q[1] + h2
    w = base + l1 * np.array([np.sin(a1), np.cos(a1)]) + l2 * np.array([np.sin(a2), np.cos(a2)])
    ang = rng.uniform(-0.5, 0.5)
    port = w + L * rng.uniform(0.35, 0.6) * np.array([np.sin(ang), np.cos(ang)])
    est = port + rng.uniform(-0.02, 0.02, 2)
    unc = {}
    if port_box:
        unc["port_y"] = sorted(rng.uniform(-0.012, 0.012, 2).tolist())
        unc["port_z"] = sorted(rng.uniform(-0.012, 0.012, 2).tolist())
    if tip_load:
        unc["tip_force_over_ei"] = sorted(rng.uniform(-4, 4, 2).tolist())
    return make_scenario_dict(
        name=f"unseen-{seed}",
        robot={"base": base.tolist(), "link_lengths": [float(l1), float(l2)], "home_angles": [float(h1), float(h2)],
               "joint_limits": [lim1, lim2], "joint_sum_limits": [float(rng.uniform(-0.6, -0.1)), float(rng.uniform(2.2, 3.0))]},
        instrument={"length": float(L)}, port={"position": port.tolist(), "estimate": est.tolist()},
        controller={"gain": float(rng.uniform(0.3, 1.5))}, uncertainty=unc, fields={"resolution": 0.016})


def _compare(doc, mf, n_port=21, n_load=7):
    pts = mf.points().reshape(-1, 2)
    v, G, P = independent_field(doc, pts, n_port, n_load)
    v, G, P = v.reshape(mf.valid.shape), G.reshape(mf.valid.shape), P.reshape(mf.valid.shape)
    both = v & mf.valid
    scale = np.maximum(1.0, G[both])
    dG = (mf.G_norm[both] - G[both]) / scale
    dP = mf.phi_max[both] - P[both]
    return {"both": int(both.sum()), "errplan_only": int((mf.valid & ~v).sum()), "indep_only": int((v & ~mf.valid).sum()),
            "dG": dG, "dP": dP, "G": G[both], "valid": mf.valid.sum()}


# ============================================================================ (a) independent check
def test_single_instance_p1_matches_independent_exactly():
    """P1 Fig. 5 setup (one error instance): errplan = the independent model to ~1e-7 everywhere."""
    doc = make_scenario_dict(fields={"resolution": 0.008})
    mf = compute_fields(parse_scenario(doc))
    c = _compare(doc, mf)
    assert c["both"] > 1000 and c["errplan_only"] == 0 and c["indep_only"] == 0
    assert np.max(np.abs(c["dG"])) < 1e-6
    assert np.max(np.abs(c["dP"])) < 1e-5


# (seed, tip-load range?, port samples per axis, load samples) of the independent dense sample
UNSEEN = [(101, False, 21, 1), (104, False, 21, 1), (115, True, 11, 5), (125, True, 11, 5)]


@pytest.mark.parametrize("seed,tip_load,n_port,n_load", UNSEEN)
def test_fields_agree_with_independent_implementation(seed, tip_load, n_port, n_load):
    """Randomized scenarios (arm, limits, shaft, port, estimate, port box, gain, tip loads):
    errplan's worst case never misses the dense-sample worst case and agrees with it to 1e-3 in
    ||G|| (relative above 1) and 3e-3 rad in |phi_max| on the common valid tips; every tip errplan
    calls valid is valid for the independent model too."""
    doc = random_doc(seed, tip_load)
    mf = compute_fields(parse_scenario(doc))
    c = _compare(doc, mf, n_port, n_load)
    assert c["both"] > 100
    assert c["errplan_only"] == 0
    assert c["indep_only"] <= 0.02 * c["both"]
    assert np.min(c["dG"]) > -TOL_G, "errplan missed a worse instance"
    assert np.min(c["dP"]) > -TOL_PHI
    # above the dense sample only where the true worst lies between its samples (near-singular tips)
    over = c["dG"] > TOL_G
    assert over.mean() < 0.05
    assert np.all(c["G"][over] > 1.0)
    assert np.max(np.abs(c["dP"])) < TOL_PHI


def test_fields_flexed_truth_without_port_box():
    """Only a tip-load range (true port = [port] position): the flexed truth against the rigid lever."""
    doc = random_doc(117, tip_load=True, port_box=False)
    mf = compute_fields(parse_scenario(doc))
    c = _compare(doc, mf, n_port=1, n_load=21)
    assert c["both"] > 100 and c["errplan_only"] == 0 and c["indep_only"] == 0
    assert np.max(np.abs(c["dG"])) < TOL_G and np.max(np.abs(c["dP"])) < TOL_PHI


# ============================================================================ (b) refinement
@pytest.fixture(scope="module")
def bounded():
    return load_scenario(SCENARIOS / "beasley2004_bounded.toml")


@pytest.mark.parametrize("which", ["bounded", "unseen-125"])
def test_worst_case_stable_under_refinement(which, bounded):
    """The worst case does not move when the error set is sampled finer: 5 vs 9 vs 17 samples per
    axis (125, 729, 4913 instances, each followed by the local refinement). unseen-125 has worst
    cases inside the box (tip loads), where the coarse sample alone is off by more than 1e-3."""
    sc = bounded if which == "bounded" else parse_scenario(random_doc(125, True))
    res = 0.016 if which == "bounded" else 0.024
    f5 = compute_fields(sc, res, samples=5)
    f9 = compute_fields(sc, res, samples=9)
    f17 = compute_fields(sc, res, samples=17)
    assert f5.valid.sum() > 100
    assert np.array_equal(f5.valid, f9.valid) and np.array_equal(f5.valid, f17.valid)
    v = f5.valid
    for f in (f9, f17):
        assert np.max(np.abs(f.G_norm[v] - f5.G_norm[v]) / np.maximum(1, f5.G_norm[v])) < 1e-3
        assert np.max(np.abs(f.phi_max[v] - f5.phi_max[v])) < 1e-3
    if which != "bounded":  # without the local refinement the coarse sample does move
        raw = compute_fields(sc, res, samples=5, refine=0)
        assert np.max((f17.G_norm[v] - raw.G_norm[v]) / np.maximum(1, f17.G_norm[v])) > 1e-3


def test_chunked_worst_case_is_the_same(bounded):
    ev = Evaluator.from_model(build_arm(bounded))
    mf = compute_fields(bounded, 0.02)
    x = mf.points()[mf.valid][:300]
    a = worst_case(ev, x, 1.0)
    b = worst_case(ev, x, 1.0, chunk=70)
    for key in ("valid", "G_norm", "phi_max", "theta_G"):
        assert np.array_equal(a[key], b[key]), key


# ============================================================================ (c) robust validity
def test_robust_validity_every_instance_reaches_every_valid_tip(bounded):
    """A tip valid in the field is reachable under every instance of a dense sample of the box
    (errplan's own evaluator, 11 x 11 x 11 instances, and the independent model on 9 x 9 x 5),
    and tips that some instance cannot reach are not valid."""
    mf = compute_fields(bounded, 0.01)
    ev = Evaluator.from_model(build_arm(bounded))
    pts = mf.points().reshape(-1, 2)
    cand = np.flatnonzero(np.isfinite(pts).all(-1) & (np.linalg.norm(pts - bounded.port.estimate, axis=-1) < 0.34))
    ok_all = np.ones(len(cand), bool)
    for th in ev.errors.sample_grid(11):
        _, ok = ev.true_wrist(pts[cand], th)
        ok_all &= ok
    valid = mf.valid.reshape(-1)[cand]
    assert np.all(ok_all[valid])
    assert np.mean(ok_all == valid) > 0.99  # the two differ only where an off-grid instance fails
    # the independent model (brute-force IK) agrees on the valid set
    doc = make_scenario_dict(port={"position": [0.0, 0.16], "estimate": [0.0, 0.16]},
                             uncertainty={"port_y": [-0.005, 0.005], "port_z": [-0.005, 0.005],
                                          "tip_force_over_ei": [-1.0, 1.0]})
    x = pts[cand][valid]
    v_ind, _, _ = independent_field(doc, x, n_port=9, n_load=5)
    assert v_ind.all()


def test_workspace_shrinks_with_the_error_set(bounded):
    small = compute_fields(bounded.with_(uncertainty=Uncertainty()), 0.01)  # the single true port
    big = compute_fields(bounded, 0.01)
    assert big.valid.sum() < small.valid.sum()
    # every robustly valid tip of the big set is valid for the single instance (grids share 0 mod res)
    pts = big.points()[big.valid]
    iy = np.rint((pts[:, 0] - small.y[0]) / 0.01).astype(int)
    iz = np.rint((pts[:, 1] - small.z[0]) / 0.01).astype(int)
    inside = (iy >= 0) & (iy < len(small.y)) & (iz >= 0) & (iz < len(small.z))
    assert inside.all() and np.all(small.valid[iy, iz])


# ============================================================================ (d) npz contract
def test_npz_keys_shapes_nan_outside_and_round_trip(tmp_path, bounded):
    mf = compute_fields(bounded, 0.01, rho_star=True)
    path = tmp_path / "f.npz"
    mf.save(path)
    with np.load(path) as d:
        keys = set(d.files)
        assert {"y", "z", "valid", "G_norm", "phi_hat_max", "phi_max", "rho_star", "k_star"} <= keys
        ny, nz = len(d["y"]), len(d["z"])
        assert d["y"].shape == (ny,) and d["z"].shape == (nz,)
        assert np.all(np.diff(d["y"]) > 0) and np.allclose(np.diff(d["y"]), 0.01)
        assert d["valid"].dtype == bool
        for name in ("valid", "G_norm", "phi_hat_max", "phi_max", "rho_star", "k_star"):
            assert d[name].shape == (ny, nz), name
        v = d["valid"]
        for name in ("G_norm", "phi_hat_max", "phi_max", "rho_star", "k_star"):
            assert np.all(np.isnan(d[name][~v])), name
            assert np.all(np.isfinite(d[name][v])), name
        assert np.all(d["phi_max"][v] <= np.pi) and np.all(d["phi_hat_max"][v] <= np.pi)
        meta = json.loads(str(d["meta"]))
        assert meta["resolution"] == 0.01 and meta["gain"] == 1.0
    back = MetricField.load(path)
    for name in ("y", "z", "valid", "G_norm", "phi_hat_max", "phi_max", "rho_star", "k_star"):
        assert np.array_equal(getattr(back, name), getattr(mf, name), equal_nan=True), name
    assert not (tmp_path / "f.npz.part").exists()
    # without --rho-star the keys are absent and asking for them is a clear error
    plain = compute_fields(bounded, 0.02)
    plain.save(tmp_path / "g.npz")
    with np.load(tmp_path / "g.npz") as d:
        assert "rho_star" not in d.files
    with pytest.raises(ErrplanError, match="rho_star"):
        MetricField.load(tmp_path / "g.npz").array("rho_star")


def test_phi_hat_max_field_is_the_transform_of_g_norm(bounded):
    from errplan.metrics import phi_hat_max
    mf = compute_fields(bounded, 0.01)
    v = mf.valid
    assert np.allclose(mf.phi_hat_max[v], phi_hat_max(mf.G_norm[v]))


def test_sample_is_bilinear_and_nan_outside():
    y = np.arange(5) * 0.01
    z = np.arange(4) * 0.01 + 0.1
    Y, Z = np.meshgrid(y, z, indexing="ij")
    lin = 2.0 * Y - 3.0 * Z + 1.0
    valid = np.ones_like(lin, bool)
    valid[4, 3] = False
    g = np.where(valid, lin, np.nan)
    mf = MetricField(y, z, valid, g, g, g, meta={"resolution": 0.01})
    pts = np.array([[0.013, 0.117], [0.0, 0.1], [0.025, 0.125]])
    assert np.allclose(mf.sample("G_norm", pts), 2 * pts[:, 0] - 3 * pts[:, 1] + 1)
    out = mf.sample("G_norm", np.array([[-0.001, 0.11], [0.035, 0.125], [0.02, 0.5]]))
    assert np.isnan(out).all()  # outside the grid, or next to an invalid corner


def test_summary_counts():
    mf = compute_fields(parse_scenario(make_scenario_dict()), 0.01)
    s = mf.summary()
    v = mf.valid
    assert s["valid_points"] == v.sum()
    assert s["share_G_below_1"] == pytest.approx(np.mean(mf.G_norm[v] < 1))
    assert s["G_norm"]["max"] == pytest.approx(np.nanmax(mf.G_norm))


def test_resolution_errors(bounded):
    with pytest.raises(ErrplanError, match="resolution"):
        compute_fields(bounded, -0.01)
    with pytest.raises(ErrplanError, match="grid would have"):
        compute_fields(bounded, 0.0001)


# ============================================================================ (e) rho*, k*
@pytest.fixture(scope="module")
def rho_field():
    sc = load_scenario(SCENARIOS / "beasley2004_bounded.toml")
    return sc, compute_fields(sc, 0.012, rho_star=True)


def test_rho_star_bounds(rho_field):
    sc, mf = rho_field
    v = mf.valid
    assert np.all(mf.rho_star[v] <= mf.G_norm[v] + 1e-9)   # the scenario gain is one of the k > 0
    assert np.all(mf.rho_star[v] <= 1.0)
    assert np.all(mf.rho_star[v] > 0)
    assert np.all((mf.k_star[v] == 0) == (mf.rho_star[v] == 1.0))
    assert np.mean(mf.rho_star[v] < 1) >= np.mean(mf.G_norm[v] < 1)


def test_rho_star_and_k_star_vs_brute_force_gain_scan(rho_field):
    """At 60 tips: rho* = min over a dense k grid of the max over a dense 9 x 9 x 9 sample of the
    error set (errplan's evaluator), and errplan's k* attains it."""
    sc, mf = rho_field
    ev = Evaluator.from_model(build_arm(sc))
    rng = np.random.default_rng(5)
    pts = mf.points()[mf.valid]
    idx = rng.choice(len(pts), 60, replace=False)
    x = pts[idx]
    rho = mf.rho_star[mf.valid][idx]
    kst = mf.k_star[mf.valid][idx]
    th = ev.errors.sample_grid(9)
    mus, nus = [], []
    for t in th:
        mu, nu, ok = ev.parts(x, t)
        assert ok.all()
        mus.append(mu)
        nus.append(nu)
    mu, nu = np.concatenate(mus, axis=1), np.concatenate(nus, axis=1)
    ks = np.linspace(0.0, 2.5, 2501)
    worst = np.array([g_norm_from_parts(mu, nu, k).max(axis=1) for k in ks])  # (nk, n)
    brute = np.minimum(worst.min(axis=0), 1.0)
    assert np.max(np.abs(rho - brute)) < 2e-3
    at_k = g_norm_from_parts(mu, nu, kst[:, None]).max(axis=1)
    assert np.all(np.where(kst > 0, at_k, 1.0) <= rho + 1e-6)


def test_minimize_gain_exact_cases():
    # one instance M = mu I (real, positive): rho* = 0 at k* = 1/mu
    mu = np.array([[2.0 + 0j], [0.5 + 0j]])
    nu = np.zeros_like(mu)
    rho, k = minimize_gain(mu, nu)
    assert np.allclose(rho, 0, atol=1e-9) and np.allclose(k, [0.5, 2.0], rtol=1e-6)
    # a pure rotation by 120 degrees: no gain contracts -> rho* = 1, k* = 0
    rot = np.exp(1j * 2 * np.pi / 3)
    rho, k = minimize_gain(np.array([[rot]]), np.zeros((1, 1), complex))
    assert rho[0] == 1.0 and k[0] == 0.0
    # two instances mu = 1 and 3: min_k max(|1-k|, |1-3k|) = 1/2 at k = 1/2
    rho, k = minimize_gain(np.array([[1.0 + 0j, 3.0 + 0j]]), np.zeros((1, 2), complex))
    assert rho[0] == pytest.approx(0.5, abs=1e-9) and k[0] == pytest.approx(0.5, abs=1e-6)


# ============================================================================ flexion controller
def test_flexion_controller_corner_worst_case_is_sound_where_certified():
    """P2's controller fed noisy end poses: errplan takes the worst over the 64 corners of the
    sensor-noise box. Where that worst case certifies contraction (< 1), 3000 uniform draws inside
    the box never do worse (||G|| is close to convex in the noise there); elsewhere interior noise
    can be far worse (the estimate degenerates), which only strengthens 'not certified'."""
    doc = make_scenario_dict(instrument={"length": 0.355}, port={"estimate": [0.0, 0.16]},
                             controller={"jacobian": "flexion"},
                             uncertainty={"tip_force_over_ei": [3.0, 3.0],
                                          "sensor_noise": {"position": 0.0005, "angle": 0.0015}})
    sc = parse_scenario(doc)
    mf = compute_fields(sc, 0.012)
    v = mf.valid
    assert np.mean(mf.G_norm[v] < 1) > 0.1
    ev = Evaluator.from_model(build_arm(sc))
    cert = mf.points()[v & (mf.G_norm < 1)]
    th = np.array([0.0, 0.0, 3.0])
    w, ok = ev.true_wrist(cert, np.broadcast_to(th, (len(cert), 3)))
    assert ok.all()
    pos, ang = 0.0005, 0.0015
    rng = np.random.default_rng(11)
    draws = rng.uniform(-1, 1, (3000, 6)) * np.array([pos] * 4 + [ang] * 2)
    from errplan.kinematics.shaft import estimate_from_ends, flexed_end_angles, flexed_jacobian
    from errplan.metrics import compose_parts, conformal_parts, inverse_parts
    port = ev.errors.port(th)
    tip, thw, tht = flexed_end_angles(w, port, ev.length, 3.0)
    mu_j, nu_j = conformal_parts(flexed_jacobian(w, port, ev.length, 3.0))
    worst = np.zeros(len(cert))
    for chunk in np.array_split(draws, 6):
        est = estimate_from_ends(w[:, None] + chunk[:, 0:2], tip[:, None] + chunk[:, 2:4],
                                 thw[:, None] + chunk[:, 4], tht[:, None] + chunk[:, 5], ev.length)
        mh, nh = conformal_parts(flexed_jacobian(w[:, None] + chunk[:, 0:2], est["port"], ev.length, est["t"]))
        imu, inu, _ = inverse_parts(mh, nh)
        mu, nu = compose_parts(mu_j[:, None], nu_j[:, None], imu, inu)
        worst = np.maximum(worst, g_norm_from_parts(mu, nu, 1.0).max(axis=1))
    assert np.all(worst <= mf.G_norm[v & (mf.G_norm < 1)] + 1e-9)
    # noise-free flexion controller: J_hat = J, so ||G|| = |1 - k| (= 0 at k = 1)
    quiet = compute_fields(parse_scenario(make_scenario_dict(
        instrument={"length": 0.355}, port={"estimate": [0.0, 0.16]}, controller={"jacobian": "flexion", "gain": 0.7},
        uncertainty={"tip_force_over_ei": [3.0, 3.0]})), 0.02)
    assert np.allclose(quiet.G_norm[quiet.valid], 0.3, atol=1e-6)
    assert np.allclose(quiet.phi_max[quiet.valid], 0.0, atol=1e-6)


def test_error_set_from_scenario_semantics():
    """interfaces.md: with a port box the true port is estimate + offset; without one it is
    [port] position (and a tip-load range alone keeps it there)."""
    sc = parse_scenario(make_scenario_dict(uncertainty={"port_y": [-0.01, 0.02]}))
    es = build_arm(sc).errors
    assert es.base_port == (0.02, 0.17) and es.lo[:2] == (-0.01, 0.0) and es.hi[:2] == (0.02, 0.0)
    assert es.active.tolist() == [True, False, False]
    sc = parse_scenario(make_scenario_dict(uncertainty={"tip_force_over_ei": [-1.0, 2.0]}))
    es = build_arm(sc).errors
    assert es.base_port == (0.0, 0.16) and es.lo[2] == -1.0 and es.hi[2] == 2.0
    grid = es.sample_grid(4)
    assert grid.shape == (4, 3) and np.allclose(grid[:, 2], np.linspace(-1, 2, 4))
    assert math.isclose(es.spacing(4)[2], 1.0)


def test_flexion_controller_matches_independent_estimation():
    """P2's flexion controller, independently: end angles from eq. (2), the estimate from eqs.
    (8)-(14), Jhat by central differences of the bisection beam at the measured wrist with the
    estimated port and load, the worst over the 64 corners of the noise box. errplan's field agrees
    to 1e-6 (relative above 1) at the tips of a random 60 whose estimates stay on the shaft."""
    L, t, pos, ang = 0.355, 3.0, 0.0005, 0.0015
    doc = make_scenario_dict(instrument={"length": L}, port={"estimate": [0.0, 0.16]},
                             controller={"jacobian": "flexion", "gain": 0.8},
                             uncertainty={"tip_force_over_ei": [t, t], "sensor_noise": {"position": pos, "angle": ang}})
    mf = compute_fields(parse_scenario(doc), 0.012)
    rng = np.random.default_rng(4)
    pts = mf.points()[mf.valid]
    pick = rng.choice(len(pts), 60, replace=False)
    x = pts[pick]
    ours = mf.G_norm[mf.valid][pick]
    p = np.array([0.0, 0.16])
    w = beam_wrist(x, p, L, t)
    J = fd_near(lambda ww: beam_tip(ww, p, L, t), w, p)
    # true end poses: chord angle, port position a along it, slopes of eq. (2) at 0 and L
    d = p - w
    rho = np.hypot(d[:, 0], d[:, 1])
    a = _bisect(lambda a: a * a + (t * a * (L - a) ** 2 / 3) ** 2 - rho * rho, 0 * rho, np.minimum(rho, L))
    b = L - a
    phi = np.arctan2(d[:, 0], d[:, 1]) + np.arctan(t * b * b / 3)
    fp = t * L / a
    slope0 = -fp / 6 * (L * b * (1 - b * b / L**2))
    slopeL = -fp / 6 * (L * b * (1 - b * b / L**2 - 3) + 3 * b * b)
    tip = w + L * np.stack([np.sin(phi), np.cos(phi)], -1)
    assert np.allclose(tip, x, atol=1e-10)
    th_w, th_t = phi + np.arctan(slope0), phi + np.arctan(slopeL)
    worst = np.full(len(x), -np.inf)
    degenerate = np.zeros(len(x), bool)
    k = 0.8
    for c in itertools.product((-pos, pos), (-pos, pos), (-pos, pos), (-pos, pos), (-ang, ang), (-ang, ang)):
        pw, pt = w + c[0:2], tip + c[2:4]
        dd = pt - pw
        ph = np.arctan2(dd[:, 0], dd[:, 1])                       # eq. (9)
        s0, sL = np.tan(th_w + c[4] - ph), np.tan(th_t + c[5] - ph)  # eqs. (13), (14)
        a_e = L * (2 * sL + s0) / (sL - s0)                         # eq. (12)
        fp_e = 2 * (s0 - sL) / (a_e * (a_e - L))                    # eq. (11), over EI
        ym = -fp_e * a_e**2 * (a_e - L) ** 2 / (3 * L)              # eq. (10)
        port_e = pw + a_e[:, None] * np.stack([np.sin(ph), np.cos(ph)], -1) \
            + ym[:, None] * np.stack([np.cos(ph), -np.sin(ph)], -1)   # eq. (8)
        t_e = fp_e * a_e / L
        degenerate |= ~((a_e > 0) & (a_e < L))                      # the estimated port is off the shaft
        Jh = fd_near(lambda ww: beam_tip(ww, port_e, L, t_e), pw, port_e)
        G = np.eye(2) - k * J @ np.linalg.inv(Jh)
        worst = np.maximum(worst, np.linalg.norm(G, 2, axis=(-2, -1)))
    assert np.all(np.isfinite(ours))
    ok = ~degenerate
    assert ok.mean() > 0.85
    assert np.max(np.abs(ours - worst)[ok] / np.maximum(1, worst[ok])) < 1e-6
    # Where some noise corner puts the estimated port off the shaft (a outside (0, L): the wrist near
    # the port) the controller's model is meaningless; errplan evaluates the beam through that port
    # anyway (flexed_geometry re-solves a from |port - wrist|), so its value there is a convention,
    # not checked here (notes/readme_foundation.md, "Left open").


# ============================================================================ compiled vs numpy search
@pytest.mark.parametrize("name", ["beasley2004_bounded.toml", "beasley2004_port.toml"])
def test_compiled_kernel_equals_the_numpy_search(name):
    """The compiled kernel (fields/kernels/) and the numpy search (fields/search.py, the general
    path) implement the same method: same robust workspace, same worst cases and rho* to rounding."""
    import errplan.fields.compute as C

    sc = load_scenario(SCENARIOS / name)
    mf = compute_fields(sc, 0.006, rho_star=True)
    P = mf.points().reshape(-1, 2)
    ref = C._numpy_tile(Evaluator.from_model(build_arm(sc)), P, sc.controller.gain, None, REFINE_LEVELS, True)
    v = mf.valid.ravel()
    assert np.array_equal(v, ref["valid"]) and v.sum() > 1000
    for key, tol in (("G_norm", 1e-12), ("phi_max", 1e-12), ("rho_star", 1e-12), ("k_star", 1e-6)):
        a, b = getattr(mf, key).ravel()[v], ref[key][v]
        assert np.max(np.abs(a - b) / np.maximum(1.0, np.abs(b))) < tol, key
