"""The shortcuts of the compiled field kernels (issue 21) against the long way, exactly where it matters.

- The 3-D lever's ||I - kM|| from its reduced form (a 2 x 2 block on span{u, v} and the value along
  u x v) equals the closed-form 3 x 3 value and numpy's SVD, at any gain, also for u and v nearly
  parallel or equal.
- A planar tip certified reachable at once (``_tip_reach2``) has every wrist the error set can need
  reachable by the exact per-instance test and by ``Arm.reachable``: sampled port offsets and loads,
  the box corners included.
- The search compiled without the exact |phi_max| (issue 17: the planner's and the demo's fields) gives
  bit for bit the ``||G||``, rho*, k* and validity of the search with it, planar and spatial.
- The straight-shaft instances computed in bulk (vectorized, ``_levers2``/``_levers3``) equal the
  one-at-a-time instances to the last bit, and the worst-||G|| refinement run as lanes
  (``_pattern_lanes``) ends every search where the one-at-a-time pattern search ends it.
"""
from __future__ import annotations


import numpy as np

from conftest import SCENARIOS
import pytest

from errplan.api import compute_fields, load_scenario
from errplan.errorset import error_set
from errplan.fields.kernels import _instance3, _planar_reachable, _tip_reach2, gnorm, gval, planar_arm_params
from errplan.kinematics import arm_for


def test_lever_reduced_norm_equals_the_full_form():
    rng = np.random.default_rng(21)
    L = 0.32
    est = np.array([0.0, 0.0, 0.16])
    Mb = np.empty((1, 3, 3))
    Pb = np.empty((1, 5))
    S = np.zeros((8, 3, 3))
    V = np.zeros((8, 3))
    checked = 0
    for i in range(3000):
        x = est + np.array([0.0, 0.0, 0.15]) + rng.uniform(-0.1, 0.1, 3)
        # port offsets from none (u = v exactly) to 1e-9 m to 1 cm
        scale = 0.0 if i % 10 == 0 else 10.0 ** rng.uniform(-9, -2)
        theta = np.concatenate([rng.uniform(-1, 1, 3) * scale, [0.0, 0.0]])
        ok, *_ = _instance3(x, theta, est, est, L, Mb, Pb, 0, S, V, True)
        if not ok:
            continue
        M = Mb[0]
        for k in (0.0, 0.3, 1.0, 1.7):
            full = gnorm(3, Mb, 0, k)
            red = gval(3, Mb, Pb, 0, k)
            svd = np.linalg.norm(np.eye(3) - k * M, 2)
            assert abs(red - full) <= 1e-12 * max(1.0, full), (x, theta, k, red, full)
            assert abs(red - svd) <= 1e-12 * max(1.0, svd), (x, theta, k, red, svd)
        checked += 1
    assert checked > 2000


def test_planar_tip_certificate_implies_every_wrist_reachable():
    sc = load_scenario(SCENARIOS / "beasley2004_bounded.toml")
    es, _ = error_set(sc)
    arm = arm_for(sc.robot)
    p = planar_arm_params(arm)
    assert p[25] == 1.0  # the arctangent-free limits apply to P1's arm
    L = float(sc.instrument.length)
    lo, hi, base = es.lo_arr, es.hi_arr, np.asarray(es.base_port, float)
    rng = np.random.default_rng(7)
    # tips over the workspace's bounding box
    tips = base + np.column_stack([rng.uniform(-0.3, 0.3, 4000), rng.uniform(-0.05, 0.3, 4000)])
    cert = np.array([_tip_reach2(t, base, lo, hi, L, p) for t in tips])
    assert (cert == 1).sum() > 200 and (cert == 2).sum() > 200
    corners = np.array([[a, b] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])])
    for t in tips[cert == 1]:
        offs = np.vstack([corners, rng.uniform(lo[:2], hi[:2], (12, 2))])
        loads = [lo[2], hi[2], 0.0, rng.uniform(lo[2], hi[2])] if len(lo) > 2 else [0.0]
        wrists = []
        for o in offs:
            port = base + o
            e = t - port
            r = np.hypot(*e)
            for tl in loads:
                if tl == 0.0:
                    wrists.append(t - L * e / r)
                    continue
                # the flexed shaft's wrist (the kernel's arithmetic): chord turned by atan(t a b / 3)
                from errplan.fields.kernels import _solve_b

                b = _solve_b(r, L, tl)
                phi = np.arctan2(e[0], e[1]) - np.arctan(tl * (L - b) * b / 3.0)
                wrists.append(t - L * np.array([np.sin(phi), np.cos(phi)]))
        wrists = np.array(wrists)
        assert all(_planar_reachable(p, w[0], w[1]) for w in wrists), t
        assert arm.reachable(wrists).all(), t


@pytest.mark.parametrize("name, res", [("beasley2004_bounded.toml", 0.01), ("phantom15_spatial.toml", 0.016)])
def test_the_search_without_phi_max_is_the_search_with_it(name, res):
    from errplan.fields import kernels

    sc = load_scenario(SCENARIOS / name)
    without = compute_fields(sc, res, metrics=("G_norm", "rho_star"), workers=1)
    with_phi = compute_fields(sc, res, metrics=("G_norm", "phi_max", "rho_star"), workers=1)
    assert without.phi_max is None and np.isfinite(with_phi.phi_max[with_phi.valid]).all()
    assert with_phi.valid.sum() > 100
    for a in ("valid", "G_norm", "rho_star", "k_star"):
        assert np.array_equal(getattr(without, a), getattr(with_phi, a), equal_nan=a != "valid"), a
    d = sc.dim
    assert kernels._TILES[d, False] is not kernels._TILES[d, True]
    assert kernels._TILES[d, False].signatures and kernels._TILES[d, True].signatures  # both copies ran


def _port_box(tmp_path, name):
    """A bundled scenario with a pure port box (no load axis): the case the bulk kernels and the lanes take."""
    import re

    text = (SCENARIOS / name).read_text(encoding="utf-8")
    if name.startswith("beasley2004"):
        text = text.replace("\n[sensors]", "\n[uncertainty]\nport_y = [-0.01, 0.01]\nport_z = [-0.01, 0.01]\nsamples = 5\n"
                            "\n[sensors]", 1)
    else:
        text = re.sub(r"^tip_force_over_ei = .*$", "", text, flags=re.M)
        text = text.replace('urdf = "phantom15.urdf"', f'urdf = "{(SCENARIOS / "phantom15.urdf").as_posix()}"')
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    sc = load_scenario(path)
    es, _ = error_set(sc)
    assert not es.active[sc.dim:].any()
    return sc, es


@pytest.mark.parametrize("name", ["beasley2004_port.toml", "phantom15_spatial.toml"])
def test_straight_shafts_in_bulk_equal_the_instances(tmp_path, name):
    """The vectorized straight-shaft kernels (_levers2/_levers3) give each instance's ||G||, wrist and
    validity to the last bit of the one-at-a-time instance and gval: tips near and far, offsets from
    zero to beyond the box, tips the shaft cannot reach."""
    from errplan.fields.compute import _kernel_args
    from errplan.fields.kernels import _instance2, _levers2, _levers3

    sc, es = _port_box(tmp_path, name)
    d = sc.dim
    ka = _kernel_args(sc, es, None)
    base, est, L = ka["base_port"], ka["est"], ka["L"]
    rng = np.random.default_rng(5)
    n = 4000
    X = base + rng.uniform(-1.1, 1.1, (n, d)) * L
    X[::7] = base + rng.normal(0, 1e-10, (len(X[::7]), d))  # at the port: r below 1e-9
    G = rng.uniform(-0.02, 0.02, (d, n)) * (rng.random(n) < 0.9)
    XS = np.ascontiguousarray(X.T)
    O = np.empty((7 if d == 2 else 4, n))
    ok = np.empty(n, bool)
    Mb, Pb, S, V = np.empty((1, d, d)), np.empty((1, 5)), np.zeros((8, 3, 3)), np.zeros((8, 3))
    for k in (1.0, 0.37):
        (_levers2 if d == 2 else _levers3)(XS, np.ascontiguousarray(G), n, base, est, L, k, O, ok)
        agree = 0
        for j in range(n):
            theta = np.zeros(3 if d == 2 else 5)
            theta[:d] = G[:, j]
            if d == 2:
                okj = _instance2(X[j], theta, base, est, L, ka["arm"], Mb, 0, S, V, True)
            else:
                okj, *w = _instance3(X[j], theta, base, est, L, Mb, Pb, 0, S, V, False)
            assert ok[j] == okj, (j, X[j], theta)
            if okj:
                assert O[0, j] == gval(d, Mb, Pb, 0, k), (j, k)
                if d == 3:
                    assert tuple(O[1:4, j]) == tuple(w)
                else:
                    assert (O[3, j], O[4, j], O[5, j], O[6, j]) == (Mb[0, 0, 0], Mb[0, 0, 1], Mb[0, 1, 0], Mb[0, 1, 1])
                # the wrist is the lever's: L back from the tip along the port->tip line
                e = X[j] - (base + G[:, j])
                assert np.allclose(O[1:d + 1, j], X[j] - L * e / np.linalg.norm(e), rtol=0, atol=1e-15)
                agree += 1
        assert agree > n // 4
        assert (~ok).sum() > n // 20


@pytest.mark.parametrize("name", ["beasley2004_port.toml", "phantom15_spatial.toml"])
def test_the_refinement_in_lanes_is_each_search_alone(tmp_path, name):
    """_pattern_lanes (through the lanes' entry, _lanes_tile) runs many worst-||G|| pattern searches together; each ends with the value and the
    validity that the one-at-a-time pattern search (_pattern) gives from the same start: starts on the
    sample grid and inside the box, tips inside and at the edge of the robust workspace (some polls
    fail there), certified and uncertified tips."""
    from errplan.fields.compute import _kernel_args
    from errplan.fields.kernels import LANE_TIPS, _LANE_TILES, _instance2, _pattern
    from errplan.fields.search import EXTRA_PASSES, REFINE_LEVELS

    sc, es = _port_box(tmp_path, name)
    d = sc.dim
    ka = _kernel_args(sc, es, None)
    base, est, L, arm, chain, rmap = ka["base_port"], ka["est"], ka["L"], ka["arm"], ka["chain"], ka["rmap"]
    valid = compute_fields(sc, 0.02 if d == 2 else 0.03, metrics=("G_norm",), workers=1)
    axes = [valid.y, valid.z] if d == 2 else [valid.x, valid.y, valid.z]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, d)
    inside = P[valid.valid.reshape(-1)]
    rng = np.random.default_rng(9)
    # tips of the robust workspace and tips up to a grid step outside it (polls fail there)
    X = np.concatenate([inside[rng.choice(len(inside), 300)],
                        inside[rng.choice(len(inside), 200)] + rng.normal(0, 0.02, (200, d))])
    ns = len(X)
    assert ns > LANE_TIPS
    grid = ka["grid"]
    na = grid.shape[1]
    TH = np.empty((na, ns))
    for s in range(ns):
        TH[:, s] = grid[rng.integers(len(grid))] if s % 2 else rng.uniform(es.lo_arr, es.hi_arr)
    TH[d:] = 0.0
    k = float(sc.controller.gain)
    Mb, Pb, S, V = np.empty((1, d, d)), np.empty((1, 5)), np.zeros((8, 3, 3)), np.zeros((8, 3))
    best = np.empty(ns)
    known = rng.random(ns) < 0.25  # a quarter as if certified (no reachability test), the rest the exact test
    for s in range(ns):
        if d == 2:
            _instance2(X[s], TH[:, s], base, est, L, arm, Mb, 0, S, V, True)
        else:
            _instance3(X[s], TH[:, s], base, est, L, Mb, Pb, 0, S, V, False)
        best[s] = gval(d, Mb, Pb, 0, k)
    best = np.where(np.isfinite(best), best, 0.0)
    alone = []
    for s in range(ns):
        th = TH[:, s].copy()
        alone.append(_pattern(d, 0, k, X[s], th, best[s], ka["step0"], es.lo_arr, es.hi_arr, es.active, es.periodic,
                              REFINE_LEVELS, EXTRA_PASSES, base, est, L, arm, chain, rmap, Mb, Pb, S, V,
                              np.empty(na), known[s]))
    b_l, live = best.copy(), np.ones(ns, bool)
    # each search its own tip here (owner s): the completed results are the searches' own
    out_valid, out_g, out_p, out_r, out_k = np.ones(ns, bool), np.empty(ns), np.empty(ns), np.empty(ns), np.empty(ns)
    # through the lanes' entry: 500 tips, two blocks of LANE_TIPS
    _LANE_TILES[d](ns, np.ascontiguousarray(X.T), np.ascontiguousarray(TH[:d]), b_l, known, live, np.arange(ns),
                   ka["step0"], es.lo_arr, es.hi_arr, es.active, es.periodic, REFINE_LEVELS, EXTRA_PASSES, base,
                   est, L, k, arm, chain, rmap, False, out_valid, out_g, out_p, out_r, out_k)
    oks = np.array([a[1] for a in alone])
    assert np.array_equal(live, oks) and np.array_equal(out_valid, oks)
    assert np.array_equal(b_l[oks], np.array([a[0] for a in alone])[oks])
    assert np.array_equal(out_g[oks], b_l[oks]) and np.isnan(out_g[~oks]).all()
    assert 100 < oks.sum() < ns  # both kinds present
    assert (b_l[oks] > best[oks]).mean() > 0.5  # the refinement climbed


@pytest.mark.parametrize("name, box, straight", [("beasley2004_port.toml", False, True),
                                                  ("beasley2004_bounded.toml", False, False),
                                                  ("phantom15_spatial.toml", False, False),
                                                  ("phantom15_spatial.toml", True, True),
                                                  ("beasley2004_bounded.toml", "fixed load", False)])
def test_the_lanes_load_where_and_only_where_the_search_records_lanes(tmp_path, monkeypatch, name, box, straight):
    """``load_lanes`` (the loader thread's: compile or load the lanes' entry before the workers fork) reads
    the error set as the compiled search does: it loads the lanes exactly when the search records some
    (straight shafts only: a port error alone) and never for an error set with a tip load (no compile the
    command cannot use)."""
    from errplan.fields import compute, kernels

    if box == "fixed load":  # a load known exactly: no load axis active, every sample loaded
        path = tmp_path / name
        path.write_text((SCENARIOS / name).read_text(encoding="utf-8").replace(
            "tip_force_over_ei = [-1.0, 1.0]", "tip_force_over_ei = [0.5, 0.5]"), encoding="utf-8")
        sc = load_scenario(path)
        es, _ = error_set(sc)
        assert not es.active[sc.dim:].any()
    elif box:
        sc, es = _port_box(tmp_path, name)
    else:
        sc = load_scenario(SCENARIOS / name)
        es, _ = error_set(sc)
    valid = compute_fields(sc, 0.02 if sc.dim == 2 else 0.03, metrics=("G_norm",), workers=1)
    axes = [valid.y, valid.z] if sc.dim == 2 else [valid.x, valid.y, valid.z]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, sc.dim)[valid.valid.reshape(-1)]
    job = compute.FieldJob(np.ascontiguousarray(P[:50]), float(sc.controller.gain), False, False, 2, None,
                           compute._kernel_args(sc, es, None))
    lanes = kernels._Lanes(sc.dim, len(job.X))
    out = [np.zeros(len(job.X), bool)] + [np.empty(len(job.X)) for _ in range(4)]
    kernels._TILES[sc.dim, False](job.X, *compute._tile_args(job), *out, *lanes.bufs)
    loaded = []
    monkeypatch.setattr(kernels.loops, "run_lanes", lambda *a: loaded.append(a))  # what load_lanes calls
    kernels.load_lanes(sc.dim, *compute._tile_args(job))
    assert (lanes.count[0] > 0) == bool(loaded) == straight


def test_gnorm_bound_above_exact_value():
    """The Frobenius bound the golden section and the pattern search skip instances by (_gval_ub) is never
    below ||I - k M||_2 (numpy's SVD) nor the kernel's value, for general 3 x 3 M, near-identity M and k over
    [0, 3]."""
    from errplan.fields.kernels import _gval_ub

    rng = np.random.default_rng(7)
    Ms = np.concatenate([rng.normal(size=(300, 3, 3)), np.eye(3) + 1e-3 * rng.normal(size=(100, 3, 3))])
    Pb = np.full((len(Ms), 5), np.nan)
    tr = np.trace(Ms, axis1=1, axis2=2).copy()
    f2 = (Ms ** 2).sum(axis=(1, 2))
    tight = 0
    for k in (0.0, 0.3, 1.0, 2.7):
        exact = np.linalg.norm(np.eye(3) - k * Ms, 2, axis=(1, 2))
        for j in range(len(Ms)):
            ub = _gval_ub(3, Pb, j, k, tr, f2)
            assert ub >= exact[j] and ub >= gval(3, Ms, Pb, j, k)
            tight += ub < 1.01 * exact[j] + 1e-6
    assert tight > 0  # tight for some (rank-one-like I - k M, k = 0): the test can fail
    Pb[0, 0] = 0.5  # a lever's reduced form: no bound needed (inf)
    assert _gval_ub(3, Pb, 0, 1.0, tr, f2) == np.inf


def test_instance3_reuse_gives_fresh_values():
    """A loaded instance after others (V holding the previous one's basis and beam) gives bit for bit the
    M and wrist of the same instance on zeroed scratch."""
    x = np.array([0.01, -0.02, 0.33])
    bp, est, L = np.array([0.0, 0.0, 0.16]), np.array([0.0, 0.0, 0.16]), 0.32
    rng = np.random.default_rng(3)
    thetas = [np.array([0.002, -0.001, 0.003, tau, psi]) for tau in (0.5, 1.0) for psi in np.linspace(0, 6, 5)]
    thetas += [np.array([*rng.uniform(-0.005, 0.005, 3), 1.0, 1.0]) for _ in range(4)]
    S, V = np.zeros((8, 3, 3)), np.zeros((9, 3))
    M, Pb = np.empty((1, 3, 3)), np.empty((1, 5))
    for th in thetas:
        r1 = _instance3(x, th, bp, est, L, M, Pb, 0, S, V, True)
        M1 = M.copy()
        r0 = _instance3(x, th, bp, est, L, M, Pb, 0, np.zeros((8, 3, 3)), np.zeros((9, 3)), True)
        assert r1 == r0 and r1[0] and np.array_equal(M1, M)


def _hard_maps(rng):
    """3 x 3 maps where a bound of ||I - k M|| is hard: general, near the identity (G small and nearly
    isotropic at k = 1), scaled rotations (G^T G a multiple of I: a triple eigenvalue), rank-one
    ``I - k M`` at k = 1, a double top singular value."""
    rot = np.linalg.qr(rng.normal(size=(60, 3, 3)))[0]
    u = rng.normal(size=(60, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    dbl = np.einsum("nij,j,nkj->nik", rot, np.array([1.3, 1.3, 0.2]), rot)
    return np.concatenate([rng.normal(size=(300, 3, 3)), np.eye(3) + 1e-3 * rng.normal(size=(100, 3, 3)),
                           np.eye(3) - 0.3 * rot, np.eye(3) - 2.0 * np.einsum("ni,nj->nij", u, u),
                           np.eye(3) - dbl])


def test_tight_gnorm_bound_never_below_the_exact_value():
    """_gnorm_below (the Laguerre bound the golden section, the certification, the pattern search and the
    lazy starts skip instances by) never says ||I - k M|| is below a threshold the exact value reaches
    (numpy's SVD, and gval's closed form the search compares), and is tight: it says so within 1e-3 of
    the value for most maps (the test can fail both ways)."""
    from errplan.fields.kernels import _gnorm_below

    Ms = _hard_maps(np.random.default_rng(11))
    Pb = np.full((len(Ms), 5), np.nan)
    tight = 0
    total = 0
    for k in (0.0, 0.3, 1.0, 1.4, 2.7):
        exact = np.linalg.norm(np.eye(3) - k * Ms, 2, axis=(1, 2))
        for j in range(len(Ms)):
            v = gval(3, Ms, Pb, j, k)
            assert v == pytest.approx(exact[j], rel=1e-12, abs=1e-14)
            for thr in (v, exact[j], max(v, exact[j]) * (1 + 1e-12), 0.5 * v):
                assert not _gnorm_below(Ms, j, k, thr)
            tight += _gnorm_below(Ms, j, k, exact[j] * (1 + 1e-3) + 1e-6)
            total += 1
    assert tight > 0.7 * total
    Ms[0, 1, 1] = np.nan  # not finite: never below (the exact value decides)
    assert not _gnorm_below(Ms, 0, 1.0, 1e300)


def _starts_reference(vals, m, na, second_start, pos, stride, counts, periodic, nbr):
    """The search's choice of its starts from every value (loops._search before the lazy values)."""
    from errplan.fields.kernels import _far, _local_max, _peak_raise

    jbest = 0
    for j in range(1, m):
        if vals[j] > vals[jbest]:
            jbest = j
    j2 = -1
    for j in range(m):
        if (j2 < 0 or vals[j] > vals[j2]) and _far(j, jbest, pos, counts, periodic, na) and _local_max(vals, j, nbr):
            j2 = j
    if j2 >= 0:
        v = vals[jbest]
        if not (vals[j2] + 2.0 * _peak_raise(vals, j2, pos, stride, counts, periodic, na)
                >= v - second_start * max(1.0, abs(v))):
            j2 = -1
    return jbest, j2


@pytest.mark.parametrize("seed", range(4))
def test_lazy_starts_are_the_starts_from_every_value(seed):
    """_starts_lazy (loaded samples' ||G|| computed only where a comparison needs them) picks the worst
    sample and the second start that the choice from every value picks, on the abdomen's grid shape
    (3 x 3 x 3 port offsets, 3 loads, 8 periodic directions), with smooth maps (several local maxima),
    rough ones, ties, and the planar-like case without a second start; NaN values: left to the caller."""
    from errplan.fields.kernels import _sample_table, _starts_lazy

    rng = np.random.default_rng(seed)
    counts = np.array([3, 3, 3, 3, 8])
    periodic = np.array([False, False, False, False, True])
    na, m = 5, int(np.prod(counts))
    pos = np.empty((m, na), np.int64)
    stride = np.empty(na, np.int64)
    nbr = np.empty((m, 2 * na), np.int64)
    _sample_table(counts, periodic, na, m, pos, stride, nbr)
    k = 1.0
    for case in range(6):
        # maps M = I + eps (a smooth field over the grid, with bumps) + noise; some samples "levers"
        ph = pos / np.maximum(counts - 1, 1)
        amp = np.sin(3.0 * ph @ rng.normal(size=na) + rng.uniform(0, 6)) + 0.5 * np.cos(2 * np.pi * pos[:, 4] / 8)
        Ms = np.eye(3) + 0.2 * amp[:, None, None] * rng.normal(size=(1, 3, 3)) \
            + (0.05 if case % 2 else 1e-4) * rng.normal(size=(m, 3, 3))
        if case == 4:
            Ms[::7] = Ms[3]  # ties: many samples with the very same value
        Pbs = np.full((m, 5), np.nan)
        vals_all = np.array([gval(3, Ms, Pbs, j, k) for j in range(m)])
        known = pos[:, 3] == 0  # the unloaded samples: known up front (their reduced form's value)
        for second_start in (0.002, 0.5, 0.0):
            vals = np.where(known, vals_all, -7.0)
            kn = known.copy()
            st = np.empty(2, np.int64)
            assert _starts_lazy(3, Ms, Pbs, k, vals, kn, m, na, second_start, pos, stride, counts, periodic, nbr, st)
            ref = _starts_reference(vals_all, m, na, second_start, pos, stride, counts, periodic, nbr) \
                if second_start > 0 else (int(np.argmax(vals_all)), -1)
            assert (st[0], st[1]) == ref
            assert np.array_equal(vals[kn], vals_all[kn])  # every value it computed is the value
            assert kn.sum() < m  # it skipped some (the test can fail)
    Ms[5, 0, 0] = np.nan
    kn = pos[:, 3] == 0
    vals = np.where(kn, np.array([gval(3, Ms, Pbs, j, k) for j in range(m)]), 0.0)
    assert not _starts_lazy(3, Ms, Pbs, k, vals, kn, m, na, 0.002, pos, stride, counts, periodic, nbr, st)


def test_golden_gain_from_the_worst_value_alone_is_the_same():
    """rho*'s golden section (_golden_gain) given every value at the scenario gain, or only the worst one
    (the lazy search's: the others are below it), returns the same rho* and k* to the bit, and the values
    it leaves at k* (which the certification reads) are gval's there."""
    from errplan.fields.kernels import _golden_gain

    rng = np.random.default_rng(5)
    for case in range(20):
        m = 40
        Ms = np.eye(3) + (0.3 if case % 2 else 0.05) * rng.normal(size=(m, 3, 3))
        Pb = np.full((m, 5), np.nan)
        v0 = np.array([gval(3, Ms, Pb, j, 1.0) for j in range(m)])
        res = []
        for kn in (np.ones(m, bool), v0 == v0.max()):
            idx = np.empty(m, np.int64)
            tr, f2, lk, lv = (np.empty(m) for _ in range(4))
            rs, ks = _golden_gain(3, Ms, Pb, m, 60, 1.0, idx, tr, f2, np.where(kn, v0, np.nan), kn, lk, lv)
            res.append((rs, ks))
            at = lk == ks
            assert np.array_equal(lv[at], [gval(3, Ms, Pb, j, ks) for j in np.flatnonzero(at)])
        assert res[0] == res[1]
        # the minimax against a scan of the gain over its bracket [0, 2 / max ||M||_F]
        ks_grid = np.linspace(0.0, 2.0 / np.sqrt((Ms ** 2).sum(axis=(1, 2))).max(), 1001)
        scan = np.linalg.norm(np.eye(3) - ks_grid[:, None, None, None] * Ms, 2, axis=(2, 3)).max(axis=1)
        assert res[0][0] <= scan.min() + 1e-9
