"""Spatial (3-D) planning (errplan.planning) against independent references, on synthetic fields.

The fields are analytic and built here (:func:`synthetic_field`), so these tests do not depend on
the spatial field computation: a robust workspace inside an ellipsoid (the invalid shell around
it), with a hole along the port axis (a cylinder of radius 15 mm around x = y = 0, the axis of
phantom15_spatial.toml's port) and a bar across y (a second hole, with a passage one or two cells
thin between it and the shell); smooth worst-case fields rising toward the port axis and with
depth, and a blob where rho_star > 1 - certify_margin.

- the exact per-cell integral of the cell walk against dense quadrature of MetricField.sample
  (trilinear) and against errplan.planning.reference's Simpson integrator; an x-extruded planar
  field against the planar walk;
- motion and point validity against dense point checks of the fields' own arrays;
- exact maxima and lengths above a threshold against dense sampling; the heuristic's admissibility;
- seeded random queries: planned cost <= 1.05 x the grid optimum (Dijkstra with long moves,
  radius 3: 290 directions), never above a usable straight line, the path inside the usable region
  between its vertices (dense check), within 2 s; the straight line through the port-axis hole is
  routed around it; two seeded runs give the same JSON;
- every error names the query and the value.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from errplan.errors import ErrplanError, InfeasibleError
from errplan.fields import MetricField
from errplan.planning import (PLANNERS, CostMap, PlannerSettings, costmap_for, make_objective, make_space_information,
                              plan_query, plan_scenario, refine_path)
from errplan.planning.reference import GridGraph, angular_bound, grid_optimum, moves, segment_cost
from errplan.scenario import Query
from errplan.api import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SPATIAL = ROOT / "scenarios" / "phantom15_spatial.toml"
HOLE = 0.015  # m, radius of the hole along the port axis


def synthetic_field(h: float = 0.005, hole: float = HOLE,
                    bounds=((-0.1, 0.1), (-0.1, 0.1), (0.26, 0.42))) -> MetricField:
    """A spatial MetricField (arrays (nx, ny, nz), NaN outside ``valid``) with analytic fields."""
    axes = [np.round(np.arange(lo, hi + 0.5 * h, h), 12) for lo, hi in bounds]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    r = np.hypot(x, y)
    inside = (x / 0.098) ** 2 + (y / 0.098) ** 2 + ((z - 0.34) / 0.079) ** 2 < 1.0
    valid = inside & (r > hole) & (np.hypot(x - 0.05, z - 0.30) > 0.012)
    bump = np.exp(-((x - 0.04) ** 2 + (y + 0.03) ** 2 + (z - 0.36) ** 2) / 0.03 ** 2)
    G = 0.25 + 1.5 * (z - 0.26) + 0.006 / (r + 0.005) + 0.5 * bump + 0.2 * np.sin(20 * x) * np.cos(15 * y)
    phi = 0.1 + 0.8 * G
    rho = 0.45 + 0.6 * np.exp(-((x + 0.05) ** 2 + (y - 0.04) ** 2 + (z - 0.36) ** 2) / 0.03 ** 2)
    nan = np.where(valid, 1.0, np.nan)
    return MetricField(axes[1], axes[2], valid, G * nan, phi * nan, 0.95 * phi * nan, rho * nan, 0.8 * nan,
                       {"resolution": h}, x=axes[0])


def random_queries(cm, graph, n: int, rng, radius: int = 3, min_dist: float = 0.05, hard_share: float = 0.5):
    """Seeded random queries in the usable region, with their grid optima; about ``hard_share`` of
    them where the straight line is not usable or the grid optimum is >= 2 % cheaper."""
    cells = np.argwhere(cm.cell_ok)
    out = []
    for _ in range(5000):
        if len(out) == n:
            break
        a, b = cells[rng.choice(len(cells), 2)]
        s = cm.origin + (a + rng.random(cm.dim)) * cm.h
        g = cm.origin + (b + rng.random(cm.dim)) * cm.h
        if np.linalg.norm(s - g) < min_dist or not cm.connected(s, g):
            continue
        ref = grid_optimum(cm, s, g, radius, graph=graph)
        ok, c = cm.path_cost([s, g])
        hard = not ok or ref.cost < 0.98 * c
        if len(out) < hard_share * n and not hard:
            continue
        out.append((tuple(s), tuple(g), ref))
    assert len(out) == n
    return out


class Problem:
    def __init__(self, mf, metric="phi_hat_max", weight=1.0, certifiable=True, radius=3):
        self.mf = mf
        self.cm = CostMap(mf, metric, weight, certifiable, 0.02)
        self.graph = GridGraph(self.cm, radius)
        self.radius = radius
        self.settings = PlannerSettings("BITstar", seed=1)

    def ref(self, s, g):
        return grid_optimum(self.cm, s, g, self.radius, graph=self.graph)


@pytest.fixture(scope="module")
def P():
    return Problem(synthetic_field())


def _segments(cm, n, rng, scale=0.04):
    """Random segments, a fifth each along a grid line through nodes, diagonal in a grid plane
    through nodes, through cell edges and corners (node to node), and general."""
    cells = np.argwhere(cm.cell_ok)
    out = []
    for k in range(n):
        c = cells[rng.integers(len(cells))]
        node = cm.origin + c * cm.h
        kind = k % 5
        if kind == 1:
            a = node
            b = a + cm.h * rng.integers(-10, 11) * np.eye(3)[rng.integers(3)]
        elif kind == 2:
            a = node
            e = np.eye(3)[rng.permutation(3)[:2]]
            b = a + cm.h * rng.integers(-8, 9) * (e[0] + rng.choice([-1, 1]) * e[1])
        elif kind == 3:
            a = node
            b = a + cm.h * rng.integers(-4, 5, 3)
        else:
            a = cm.origin + (c + rng.random(3)) * cm.h
            b = a + rng.normal(0, scale, 3)
        out.append((np.asarray(a, float), np.asarray(b, float)))
    return out


def _inside_usable(mf, ok_node, pts, h, tol=1e-7):
    """For each point: is it in a closed cell whose 8 corners are usable (from the field arrays)?"""
    axes = mf.axes
    out = np.zeros(len(pts), bool)
    for k, p in enumerate(pts):
        u = [(p[i] - axes[i][0]) / h for i in range(3)]
        cand = [[math.floor(v)] + ([math.floor(v) - 1] if v - math.floor(v) < tol else [])
                + ([math.floor(v) + 1] if math.ceil(v) - v < tol and math.ceil(v) != math.floor(v) else []) for v in u]
        for i in cand[0]:
            for j in cand[1]:
                for l in cand[2]:
                    if (0 <= i < len(axes[0]) - 1 and 0 <= j < len(axes[1]) - 1 and 0 <= l < len(axes[2]) - 1
                            and ok_node[i:i + 2, j:j + 2, l:l + 2].all()):
                        out[k] = True
                        break
                if out[k]:
                    break
            if out[k]:
                break
    return out


def _dense(path, step):
    path = np.asarray(path, float)
    return np.concatenate([a + (b - a) * np.linspace(0, 1, max(2, int(np.linalg.norm(b - a) / step) + 2))[:, None]
                           for a, b in zip(path[:-1], path[1:])])


def _ok_nodes(P):
    """Usable nodes read from the field arrays (not from the CostMap)."""
    mf = P.mf
    return mf.valid & (mf.rho_star <= 1 - P.cm.certify_margin) if P.cm.certifiable else mf.valid.copy()


# ----------------------------------------------------------------------------- cost and validity
def test_segment_cost_is_the_integral_of_the_trilinear_field(P):
    cm, mf = P.cm, P.mf
    rng = np.random.default_rng(0)
    n_valid = 0
    for a, b in _segments(cm, 100, rng):
        ok, c = cm.segment(*a, *b)
        if not ok:
            continue
        n_valid += 1
        t = np.linspace(0.0, 1.0, 20001)
        pts = a + (b - a) * t[:, None]
        f = 1.0 + cm.weight * mf.sample(cm.metric, pts)
        if not np.all(np.isfinite(f)):  # a point on a face whose far side is invalid: sample() picks that side
            f = np.array([cm.integrand_at(*p) for p in pts])
        ref = np.trapezoid(f, t) * float(np.linalg.norm(b - a))
        assert c == pytest.approx(ref, rel=1e-7, abs=1e-12)
    assert n_valid > 30


def test_segment_matches_the_independent_simpson_integrator(P):
    cm = P.cm
    rng = np.random.default_rng(1)
    agree_valid = agree_invalid = 0
    for a, b in _segments(cm, 400, rng, scale=0.06):
        ok1, c1 = cm.segment(*a, *b)
        ok2, c2 = segment_cost(cm, a, b)
        assert ok1 == ok2, (a, b)
        if ok1:
            assert c1 == pytest.approx(c2, rel=1e-10)
            agree_valid += 1
        else:
            agree_invalid += 1
        # unchecked cost of an invalid segment is finite and at least its length
        assert cm.segment(*a, *b, check=False)[1] >= np.linalg.norm(b - a) * (1 - 1e-12)
    assert agree_valid > 100 and agree_invalid > 50


def test_extruded_planar_field_gives_the_planar_costs():
    """One planner for both dimensions: a 3-D field constant along x gives, for motions at fixed x,
    the costs and validity of the planar walk on the 2-D field."""
    f2 = synthetic_field(h=0.005)
    k = 20  # the planar slice x = 0
    mf2 = MetricField(f2.y, f2.z, f2.valid[k], f2.G_norm[k], f2.phi_hat_max[k], f2.phi_max[k], f2.rho_star[k],
                      f2.k_star[k], {"resolution": 0.005})
    ext = lambda a: np.repeat(a[k][None], 3, axis=0)  # noqa: E731
    mf3 = MetricField(f2.y, f2.z, ext(f2.valid), ext(f2.G_norm), ext(f2.phi_hat_max), ext(f2.phi_max),
                      ext(f2.rho_star), ext(f2.k_star), {"resolution": 0.005}, x=np.array([-0.005, 0.0, 0.005]))
    cm2, cm3 = CostMap(mf2), CostMap(mf3)
    assert cm2.dim == 2 and cm3.dim == 3
    rng = np.random.default_rng(7)
    cells = np.argwhere(cm2.cell_ok)
    n_valid = 0
    for _ in range(300):
        i, j = cells[rng.integers(len(cells))]
        a = cm2.origin + (np.array([i, j]) + rng.random(2)) * cm2.h
        b = a + rng.normal(0, 0.04, 2)
        x = float(rng.uniform(-0.004, 0.004))
        ok2, c2 = cm2.segment(*a, *b)
        ok3, c3 = cm3.segment(x, *a, x, *b)
        assert ok2 == ok3
        assert cm2.segment(*a, *b, check=False)[1] == pytest.approx(cm3.segment(x, *a, x, *b, check=False)[1],
                                                                     rel=1e-12)
        n_valid += ok2
        assert cm2.point_ok(*b) == cm3.point_ok(x, *b)
    assert n_valid > 100


def test_valid_motions_stay_in_the_usable_region_densely(P):
    cm, mf = P.cm, P.mf
    ok_node = _ok_nodes(P)
    rng = np.random.default_rng(2)
    seen_valid = seen_invalid = 0
    for a, b in _segments(cm, 150, rng, scale=0.05):
        ok = cm.motion_ok(*a, *b)
        inside = _inside_usable(mf, ok_node, _dense([a, b], cm.h / 20), cm.h)
        if ok:
            seen_valid += 1
            assert inside.all(), (a, b)
        else:
            seen_invalid += 1
            assert not inside.all(), (a, b)
    assert seen_valid > 40 and seen_invalid > 20


def test_point_validity_against_the_field_arrays(P):
    cm, mf = P.cm, P.mf
    ok_node = _ok_nodes(P)
    rng = np.random.default_rng(3)
    lo, hi = cm.origin, cm.origin + (np.array(cm.shape) - 1) * cm.h
    pts = rng.uniform(lo, hi, (1500, 3))
    pts[::3] = np.round((pts[::3] - lo) / cm.h) * cm.h + lo  # grid nodes
    pts[1::3, 0] = np.round((pts[1::3, 0] - lo[0]) / cm.h) * cm.h + lo[0]  # on grid planes
    ours = np.array([cm.point_ok(*p) for p in pts])
    assert np.array_equal(ours, _inside_usable(mf, ok_node, pts, cm.h))
    assert 0.2 < ours.mean() < 0.8


def test_field_max_and_length_above_against_dense_sampling(P):
    cm, mf = P.cm, P.mf
    rng = np.random.default_rng(4)
    checked = 0
    for a, b in _segments(cm, 80, rng, scale=0.05):
        if not cm.motion_ok(*a, *b) or np.linalg.norm(b - a) < 1e-6:
            continue
        t = np.linspace(0, 1, 40001)
        g = mf.sample("G_norm", a + (b - a) * t[:, None])
        g = g[np.isfinite(g)]
        if len(g) < 0.99 * len(t):
            continue
        exact = cm.field_max("G_norm", [a, b])
        assert g.max() - 1e-12 <= exact <= g.max() + 1e-6
        thr = float(np.median(g))
        above = cm.field_length_above("G_norm", [a, b], thr)
        dense = float(np.mean(g >= thr) * np.linalg.norm(b - a))
        assert above == pytest.approx(dense, abs=2e-4 * np.linalg.norm(b - a) + 1e-9)
        checked += 1
    assert checked > 20


def test_heuristic_is_admissible(P):
    cm = P.cm
    space, si = make_space_information(cm)
    obj = make_objective(si, cm)
    rng = np.random.default_rng(5)
    s1, s2 = space.allocState(), space.allocState()
    for a, b in _segments(cm, 100, rng, scale=0.08):
        for k in range(3):
            s1[k], s2[k] = a[k], b[k]
        h = obj.motionCostHeuristic(s1, s2).value()
        c = obj.motionCost(s1, s2).value()
        assert h <= c + 1e-15
        assert c == pytest.approx(cm.segment(*a, *b, check=False)[1], rel=1e-14)


# ----------------------------------------------------------------------------- the reference
def test_grid_reference(P):
    cm = P.cm
    assert len(moves(2, 3)) == 98 and len(moves(3, 3)) == 290
    assert angular_bound(3, 3) == pytest.approx(0.0248, abs=1e-4) and angular_bound(4) < 0.008
    s, g = (-0.05, -0.05, 0.30), (0.05, 0.04, 0.38)
    r2 = grid_optimum(cm, s, g, 2)
    r3 = P.ref(s, g)
    assert r3.cost <= r2.cost + 1e-12
    assert cm.path_ok(r3.path)
    assert cm.path_cost(r3.path)[1] == pytest.approx(r3.cost, rel=1e-10)
    # the continuous optimum is below the reference by at most the angular bound
    rr = refine_path(cm, r3.path)
    assert r3.cost * (1 - angular_bound(3, 3)) <= rr.cost <= r3.cost


# ----------------------------------------------------------------------------- quality
def _check_plan(P, qp, ref):
    cm = P.cm
    assert qp.planned.valid and qp.planned.in_workspace
    assert cm.path_ok(qp.planned.path)
    assert np.allclose(qp.planned.path[0], qp.start) and np.allclose(qp.planned.path[-1], qp.goal)
    ok, c = cm.path_cost(qp.planned.path)
    assert ok and c == pytest.approx(qp.planned.cost, rel=1e-12)
    assert qp.planned.cost <= 1.05 * ref.cost, (qp.name, qp.planned.cost / ref.cost)
    if qp.direct.valid:
        assert qp.planned.cost <= qp.direct.cost * (1 + 1e-12)
    assert _inside_usable(P.mf, _ok_nodes(P), _dense(qp.planned.path, cm.h / 10), cm.h).all()
    # the budget is counted (speed is measured in benchmarks/planning.py)
    assert qp.stopped_by != "time" and qp.reproducible


def test_random_queries_are_near_the_grid_optimum(P):
    rng = np.random.default_rng(10)
    for k, (s, g, ref) in enumerate(random_queries(P.cm, P.graph, 6, rng)):
        qp = plan_query(P.cm, s, g, replace(P.settings, seed=10 + k), f"random{k}")
        _check_plan(P, qp, ref)


def test_straight_line_through_the_port_axis_hole_is_routed_around_it(P):
    s, g = (-0.06, 0.0, 0.33), (0.06, 0.0, 0.33)
    qp = plan_query(P.cm, s, g, P.settings, "across the port axis")
    assert not qp.direct.in_workspace and qp.direct.cost is None and qp.direct.max_G_norm is None
    _check_plan(P, qp, P.ref(s, g))
    pts = _dense(qp.planned.path, 0.0005)
    assert np.hypot(pts[:, 0], pts[:, 1]).min() >= HOLE - 1e-9
    assert qp.planned.length < 1.5 * qp.direct.length
    js = qp.to_json()
    json.dumps(js)  # no NaN
    assert js["direct"]["cost"] is None and all(len(p) == 3 for p in js["planned"]["path"])


@pytest.mark.slow
def test_other_planners_and_a_stronger_objective():
    """G_norm with weight 4, not certifiable; every planner of PLANNERS on three queries."""
    Q = Problem(synthetic_field(), "G_norm", 4.0, certifiable=False)
    queries = random_queries(Q.cm, Q.graph, 3, np.random.default_rng(30))
    for name in PLANNERS:
        for k, (s, g, ref) in enumerate(queries):
            qp = plan_query(Q.cm, s, g, replace(Q.settings, planner=name, seed=k), f"{name}-{k}")
            _check_plan(Q, qp, ref)


def test_two_seeded_runs_give_the_same_json(P):
    s, g = (-0.05, -0.05, 0.30), (0.05, 0.04, 0.38)
    st = replace(P.settings, iterations=1500, seed=3)
    a = plan_query(P.cm, s, g, st, "q")
    b = plan_query(P.cm, s, g, st, "q")
    assert a.stopped_by == b.stopped_by == "iterations"  # 1500 iterations take about 0.15 s here
    assert json.dumps(a.to_json(timing=False)) == json.dumps(b.to_json(timing=False))
    c = plan_query(P.cm, s, g, replace(st, seed=4), "q")
    assert c.raw_cost != a.raw_cost  # the seed matters to the search


def test_without_the_grid_seed_the_planner_still_routes_around_the_hole(P):
    s, g = (-0.06, 0.0, 0.33), (0.06, 0.0, 0.33)
    qp = plan_query(P.cm, s, g, replace(P.settings, grid_seed=False), "q")
    assert qp.seed_cost is None and qp.source in ("planner", "first solution")
    assert qp.planned.valid and qp.planned.cost <= 1.05 * P.ref(s, g).cost


# ----------------------------------------------------------------------------- errors
def test_start_outside_the_grid(P):
    with pytest.raises(InfeasibleError, match=r"query 'q': start \[0\.5000, 0\.0000, 0\.3000\] m is outside the field "
                                              r"grid \(x in \[-0\.100, 0\.100\], y in .*z in .* m\)"):
        plan_query(P.cm, (0.5, 0.0, 0.3), (0.05, 0.0, 0.33), P.settings, "query 'q'")


def test_goal_in_the_port_axis_hole_says_how_far(P):
    with pytest.raises(InfeasibleError, match=r"query 'q': goal \[0\.0000, 0\.0020, 0\.3300\] m is outside the robust "
                                              r"workspace .* mm away") as e:
        plan_query(P.cm, (0.05, 0.0, 0.33), (0.0, 0.002, 0.33), P.settings, "query 'q'")
    mm = float(str(e.value).rsplit(",", 1)[1].split("mm")[0])
    assert 10.0 < mm < 25.0  # 13 mm to the hole's rim, plus up to a cell to the nearest usable cell


def test_start_where_no_gain_certifies(P):
    p = (-0.05, 0.04, 0.36)  # the centre of the blob, rho_star = 1.05
    with pytest.raises(InfeasibleError, match=r"query 'q': start .*no gain can certify.*rho_star = 1\.0\d+ > "
                                              r"1 - certify_margin = 0\.98"):
        plan_query(P.cm, p, (0.05, 0.0, 0.33), P.settings, "query 'q'")
    # without the restriction the same start is fine
    assert CostMap(P.mf, certifiable=False).explain_point(p) is None


def test_no_path_within_the_budget_is_an_error(P):
    st = replace(P.settings, iterations=1, grid_seed=False)
    with pytest.raises(InfeasibleError, match=r"query 'q': BITstar found no path from \[-0\.06, 0\.0, 0\.33\] to "
                                              r"\[0\.06, 0\.0, 0\.33\] within the budget"):
        plan_query(P.cm, (-0.06, 0.0, 0.33), (0.06, 0.0, 0.33), st, "query 'q'")


def test_disconnected_endpoints(P):
    mf = P.mf
    valid = mf.valid.copy()
    k = int(np.searchsorted(mf.z, 0.34))
    valid[:, :, k:k + 2] = False
    cut = replace(mf, valid=valid)
    with pytest.raises(InfeasibleError, match="query 'q': .*disconnected parts of the usable region"):
        plan_query(CostMap(cut), (-0.05, -0.05, 0.30), (-0.05, -0.05, 0.38), P.settings, "query 'q'")


def test_wrong_dimension(P):
    with pytest.raises(InfeasibleError, match=r"query 'q': start \[0\.05, 0\.3\] has 2 coordinates, expected 3 "
                                              r"\(\[x, y, z\]\)"):
        plan_query(P.cm, (0.05, 0.3), (0.05, 0.0, 0.33), P.settings, "query 'q'")


# ----------------------------------------------------------------------------- scenario level
def test_plan_scenario_on_a_spatial_scenario(P):
    sc = load_scenario(SPATIAL)
    assert sc.dim == 3
    sc = replace(sc, queries=(Query("around", (-0.06, 0.0, 0.33), (0.06, 0.0, 0.33)),
                              Query("low", (0.01, -0.023, 0.28), (0.066, -0.016, 0.306))))
    plan = plan_scenario(sc, P.mf, settings=P.settings)
    doc = json.loads(json.dumps(plan.to_json()))
    assert "trilinear" in doc["objective"]["definition"]
    for q in doc["queries"]:
        assert len(q["start"]) == 3 and all(len(p) == 3 for p in q["planned"]["path"])
        assert q["planned"]["valid"] and q["planned"]["cost"] > 0
    bad = replace(sc, queries=(Query("in the hole", (0.0, 0.0, 0.33), (0.06, 0.0, 0.33)),))
    with pytest.raises(InfeasibleError, match=r"query 'in the hole': start \[0\.0000, 0\.0000, 0\.3300\] m is "
                                              r"outside the robust workspace"):
        plan_scenario(bad, P.mf, settings=P.settings)
    planar = MetricField(P.mf.y, P.mf.z, P.mf.valid[20], P.mf.G_norm[20], P.mf.phi_hat_max[20], P.mf.phi_max[20],
                         P.mf.rho_star[20], P.mf.k_star[20], {"resolution": 0.005})
    with pytest.raises(ErrplanError, match="the fields are 2-D but the scenario is 3-D"):
        costmap_for(sc, planar)


def test_fmt_samples_come_from_the_settings_not_the_clock(P, monkeypatch):
    """FMT*'s sample set is sized from the search's iteration budget (both phases of a query: the whole
    budget), so a loaded machine draws the same samples: 300 for FMT*'s default 1500 iterations."""
    from errplan.planning import ompl_adapter

    seen = []
    real = ompl_adapter.make_planner
    monkeypatch.setattr(ompl_adapter, "make_planner", lambda name, si, n: (seen.append(n), real(name, si, n))[1])
    st = replace(P.settings, planner="FMT", seed=1)
    plan_query(P.cm, (-0.05, -0.05, 0.30), (0.05, 0.04, 0.38), st, "q")
    assert seen and all(n == st.iteration_cap(3) == 1500 for n in seen), seen
    assert ompl_adapter.fmt_samples(1500) == 300 and ompl_adapter.fmt_samples(10) == 100
