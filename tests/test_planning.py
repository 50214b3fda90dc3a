"""Planning on the worst-case fields (errplan.planning) against independent references.

- the exact per-cell integral of CostMap.segment against dense quadrature of MetricField.sample and
  against errplan.planning.reference's Simpson integrator (a separate implementation);
- motion validity against dense point checks of the fields' own arrays;
- every bundled query and seeded random queries: planned cost <= 1.05 x the grid optimum
  (errplan.planning.reference.grid_optimum, Dijkstra with 48-connected long moves), never more than 5 %
  above a valid direct path, paths inside the usable region between vertices;
- the detour queries of beasley2004_port.toml, errors, JSON keys, determinism.
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
from errplan.planning import (PLANNERS, CostMap, PlannerSettings, costmap_for, fields_for_planning,
                              make_objective, make_space_information, plan_query, plan_scenario, refine_path)
from errplan.planning.reference import GridGraph, angular_bound, grid_optimum, moves, segment_cost
from errplan.api import load_scenario

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"
BOUNDED = ROOT / "scenarios" / "beasley2004_bounded.toml"


class Problem:
    """A scenario with its fields, cost map and reference graph (built once per module)."""

    def __init__(self, path, resolution=None):
        self.sc = load_scenario(path)
        self.mf = fields_for_planning(self.sc, resolution)
        self.cm = costmap_for(self.sc, self.mf)
        self.graph = GridGraph(self.cm, 4)
        self.settings = PlannerSettings.from_model(self.sc)

    def ref(self, s, g):
        return grid_optimum(self.cm, s, g, 4, graph=self.graph)


@pytest.fixture(scope="module")
def port():
    return Problem(PORT)  # the scenario's 2 mm grid (0.1 s: a single error instance)


@pytest.fixture(scope="module")
def bounded():
    return Problem(BOUNDED, 0.004)  # 4 mm: 1 s instead of 4 s for the 125-instance error set


def _random_segments(cm, n, rng, scale=0.03):
    cells = np.argwhere(cm.cell_ok)
    out = []
    for k in range(n):
        i, j = cells[rng.integers(len(cells))]
        a = np.array([cm.y0 + (i + rng.random()) * cm.h, cm.z0 + (j + rng.random()) * cm.h])
        b = a + rng.normal(0, scale, 2)
        if k % 5 == 1:  # along a grid line through grid nodes
            a = np.array([cm.y0 + i * cm.h, cm.z0 + j * cm.h])
            b = a + np.array([0.0, cm.h * rng.integers(-12, 12)])
        elif k % 5 == 2:
            a = np.array([cm.y0 + i * cm.h, cm.z0 + j * cm.h])
            d = rng.integers(-8, 8)
            b = a + cm.h * np.array([d, d * rng.choice([-1, 1])])
        out.append((a, b))
    return out


def _random_queries(P, n, rng, hard_share=0.5, min_dist=0.05):
    """Seeded random queries in the usable region; about ``hard_share`` of them where the grid
    optimum is >= 2 % cheaper than the straight line or the straight line is not usable."""
    cm = P.cm
    cells = np.argwhere(cm.cell_ok)
    out = []
    tries = 0
    while len(out) < n and tries < 3000:
        tries += 1
        (i, j), (k, l) = cells[rng.choice(len(cells), 2)]
        s = (cm.y0 + (i + rng.random()) * cm.h, cm.z0 + (j + rng.random()) * cm.h)
        g = (cm.y0 + (k + rng.random()) * cm.h, cm.z0 + (l + rng.random()) * cm.h)
        if math.dist(s, g) < min_dist or not cm.connected(s, g):
            continue
        ref = P.ref(s, g)
        ok, c = cm.path_cost([s, g])
        hard = not ok or ref.cost < 0.98 * c
        want_hard = len(out) < hard_share * n
        if want_hard and not hard:
            continue
        out.append((s, g, ref))
    assert len(out) == n
    return out


# ----------------------------------------------------------------------------- cost and validity
def test_segment_cost_is_the_integral_of_the_bilinear_field(port):
    cm, mf = port.cm, port.mf
    rng = np.random.default_rng(0)
    n_valid = 0
    for a, b in _random_segments(cm, 120, rng):
        ok, c = cm.segment(*a, *b)
        if not ok:
            continue
        n_valid += 1
        t = np.linspace(0.0, 1.0, 40001)
        # Sample strictly inside the segment's cells: MetricField.sample picks the cell by floor(),
        # which at a grid line can be the unusable neighbour.
        pts = a + (b - a) * t[:, None]
        f = 1.0 + cm.weight * mf.sample(cm.metric, pts)
        if not np.all(np.isfinite(f)):
            f = np.array([cm.integrand_at(*p) for p in pts])
        ref = np.trapezoid(f, t) * float(np.hypot(*(b - a)))
        assert c == pytest.approx(ref, rel=1e-7, abs=1e-12)
    assert n_valid > 40


def test_segment_matches_the_independent_simpson_integrator(port, bounded):
    rng = np.random.default_rng(1)
    for P in (port, bounded):
        cm = P.cm
        agree_valid = agree_invalid = 0
        for a, b in _random_segments(cm, 200, rng, scale=0.05):
            ok1, c1 = cm.segment(*a, *b)
            ok2, c2 = segment_cost(cm, a, b)
            assert ok1 == ok2, (a, b)
            if ok1:
                assert c1 == pytest.approx(c2, rel=1e-10)
                agree_valid += 1
            else:
                agree_invalid += 1
        assert agree_valid > 50 and agree_invalid > 5


def test_valid_motions_stay_in_the_usable_region_densely(port):
    """A motion the validator accepts has every dense point inside a cell whose four corners are in
    the robust workspace and certifiable (read from the MetricField arrays, not the CostMap)."""
    cm, mf = port.cm, port.mf
    ok_node = mf.valid & (mf.rho_star <= 1 - port.sc.planner.certify_margin)
    rng = np.random.default_rng(2)
    seen_invalid = 0
    for a, b in _random_segments(cm, 150, rng, scale=0.06):
        ok = cm.motion_ok(*a, *b)
        t = np.linspace(0, 1, max(2, int(np.hypot(*(b - a)) / (cm.h / 50))))
        pts = a + (b - a) * t[:, None]
        u = (pts[:, 0] - mf.y[0]) / cm.h
        v = (pts[:, 1] - mf.z[0]) / cm.h
        inside = np.ones(len(pts), bool)
        for k, (uu, vv) in enumerate(zip(u, v)):
            cands = [(math.floor(uu) - di, math.floor(vv) - dj) for di in (0, 1) for dj in (0, 1)
                     if (di == 0 or uu - math.floor(uu) < 1e-7) and (dj == 0 or vv - math.floor(vv) < 1e-7)]
            inside[k] = any(0 <= i < len(mf.y) - 1 and 0 <= j < len(mf.z) - 1
                            and ok_node[i, j] and ok_node[i + 1, j] and ok_node[i, j + 1] and ok_node[i + 1, j + 1]
                            for i, j in cands)
        if ok:
            assert inside.all(), (a, b)
        else:
            seen_invalid += 1
            assert not inside.all(), (a, b)
    assert seen_invalid > 10


def test_field_max_is_the_maximum_along_the_path(port):
    cm, mf = port.cm, port.mf
    rng = np.random.default_rng(3)
    for a, b in _random_segments(cm, 60, rng):
        if not cm.motion_ok(*a, *b):
            continue
        exact = cm.field_max("G_norm", [a, b])
        t = np.linspace(0, 1, 20001)
        dense = np.array([cm_val for cm_val in mf.sample("G_norm", a + (b - a) * t[:, None])])
        dense = dense[np.isfinite(dense)]
        assert exact >= dense.max() - 1e-12
        assert exact <= dense.max() + 1e-6


def test_length_above_threshold_against_dense_sampling(port):
    cm, mf = port.cm, port.mf
    a, b = np.array([-0.06, 0.40]), np.array([0.12, 0.40])
    exact = cm.field_length_above("G_norm", [a, b], 1.0)
    t = np.linspace(0, 1, 200001)
    g = mf.sample("G_norm", a + (b - a) * ((t[1:] + t[:-1]) / 2)[:, None])
    dense = float(np.sum(g >= 1.0) * (t[1] - t[0]) * np.hypot(*(b - a)))
    assert exact == pytest.approx(dense, abs=2e-5)
    assert 0.03 < exact < 0.18


def test_heuristic_is_admissible(port):
    cm = port.cm
    space, si = make_space_information(cm)
    obj = make_objective(si, cm)
    rng = np.random.default_rng(4)
    s1, s2 = space.allocState(), space.allocState()
    for a, b in _random_segments(cm, 100, rng, scale=0.08):
        s1[0], s1[1] = a
        s2[0], s2[1] = b
        assert obj.motionCostHeuristic(s1, s2).value() <= obj.motionCost(s1, s2).value() + 1e-15


# ----------------------------------------------------------------------------- the reference
def test_grid_reference_is_near_the_continuous_optimum(port):
    """Larger move sets can only lower the grid optimum; the planner's refined (continuous) path
    is never more than the angular bound below it, so the reference is within that of the truth."""
    cm = port.cm
    s, g = (-0.06, 0.40), (0.12, 0.40)
    costs = [grid_optimum(cm, s, g, r).cost for r in (2, 3, 4, 6)]
    assert all(b <= a + 1e-12 for a, b in zip(costs, costs[1:]))
    ref = port.ref(s, g)
    assert cm.path_ok(ref.path)
    assert cm.path_cost(ref.path)[1] == pytest.approx(ref.cost, rel=1e-10)
    assert len(moves(4)) == 48 and angular_bound(4) < 0.008
    qp = plan_query(cm, s, g, port.settings)
    assert qp.planned.cost >= ref.cost * (1 - angular_bound(4))
    assert qp.planned.cost <= ref.cost * 1.05


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
        assert qp.planned.cost <= 1.05 * qp.direct.cost
    # The budget: counted, never the clock without a time cap (speed is measured in benchmarks/planning.py).
    st = P.settings
    assert st.time is None and qp.stopped_by in ("iterations", "planner") and qp.reproducible
    assert qp.iterations <= st.iteration_cap(cm.dim)


@pytest.mark.parametrize("which", ["port", "bounded"])
def test_every_bundled_query_is_near_the_grid_optimum(which, request):
    P = request.getfixturevalue(which)
    assert P.settings.planner == "BITstar" and P.settings.iteration_cap(2) == 7500
    for q in P.sc.queries:
        qp = plan_query(P.cm, q.start, q.goal, P.settings, q.name)
        _check_plan(P, qp, P.ref(q.start, q.goal))


@pytest.mark.parametrize("which,seed", [("port", 10), ("bounded", 20)])
def test_random_queries_are_near_the_grid_optimum(which, seed, request):
    P = request.getfixturevalue(which)
    rng = np.random.default_rng(seed)
    for k, (s, g, ref) in enumerate(_random_queries(P, 6, rng)):
        qp = plan_query(P.cm, s, g, replace(P.settings, seed=seed + k), f"random{k}")
        _check_plan(P, qp, ref)


@pytest.mark.slow
def test_random_queries_other_metrics_and_planners(port):
    """G_norm with a large weight (stronger detours), not certifiable; every planner of PLANNERS but
    FMT and BFMT (their fixed sample set needs more than their default budget on this objective), each at
    its own default budget (the scenario's iterations are BITstar's: 40 times the RRT* family's). Each
    planner plans one of the two hard queries (the grid optimum well below the straight line) and one of
    the two others, alternating, so that every query is planned by more than one planner."""
    mf = port.mf
    cm = CostMap(mf, "G_norm", 4.0, certifiable=False)
    P = Problem.__new__(Problem)
    P.sc, P.mf, P.cm, P.graph = port.sc, mf, cm, GridGraph(cm, 4)
    P.settings = port.settings
    rng = np.random.default_rng(30)
    queries = _random_queries(P, 4, rng)
    for name in PLANNERS:
        if name in ("FMT", "BFMT"):
            continue
        i = PLANNERS.index(name)
        for k in (i % 2, 2 + (i + 1) % 2):
            s, g, ref = queries[k]
            qp = plan_query(cm, s, g, replace(port.settings, planner=name, seed=k, iterations=None),
                            f"{name}-{k}")
            _check_plan(P, qp, ref)


# ----------------------------------------------------------------------------- detours
def test_across_deep_detour_pays_off(port):
    """Across the deep part of P1's workspace the straight line spends most of its length where the
    worst-case ||G|| >= 1; the plan leaves that band early: much cheaper, modestly longer."""
    q = {q.name: q for q in port.sc.queries}["across-deep"]
    qp = plan_query(port.cm, q.start, q.goal, port.settings, q.name)
    P, D = qp.planned, qp.direct
    assert D.valid
    assert P.cost < 0.85 * D.cost
    assert P.length < 1.12 * D.length
    assert P.length_G_above_1 < 0.5 * D.length_G_above_1
    assert D.length_G_above_1 > 0.3 * D.length
    # max ||G|| is attained at the start (both ends are in the band), so it is the same
    assert P.max_G_norm == pytest.approx(D.max_G_norm, rel=1e-9)


def test_past_the_port_detour_lowers_max_G(port):
    q = {q.name: q for q in port.sc.queries}["past-the-port"]
    qp = plan_query(port.cm, q.start, q.goal, port.settings, q.name)
    P, D = qp.planned, qp.direct
    assert D.valid
    ends = float(np.max(port.mf.sample("G_norm", np.array([q.start, q.goal]))))
    assert D.max_G_norm > ends + 0.02  # the straight line passes a higher-error region
    assert P.max_G_norm < D.max_G_norm - 0.01
    assert P.length < 1.01 * D.length
    assert P.cost < D.cost


def test_around_the_port_direct_leaves_the_workspace(port):
    """The straight line crosses the unreachable region around the port: the plan goes around it,
    the direct path's cost and maxima are reported as undefined (null in JSON)."""
    qp = plan_query(port.cm, (-0.04, 0.20), (0.05, 0.23), port.settings, "around")
    assert not qp.direct.in_workspace and qp.direct.cost is None and qp.direct.max_G_norm is None
    assert qp.planned.valid and qp.planned.length < 1.6 * qp.direct.length
    js = qp.to_json()
    json.dumps(js)  # no NaN
    assert js["direct"]["cost"] is None and js["direct"]["valid"] is False


# ----------------------------------------------------------------------------- errors
def test_start_outside_the_grid(port):
    with pytest.raises(InfeasibleError, match=r"start \[0\.5000, 0\.4000\] m is outside the field grid"):
        plan_query(port.cm, (0.5, 0.4), (0.0, 0.3), port.settings)


def test_goal_outside_the_robust_workspace_says_how_far(port):
    with pytest.raises(InfeasibleError, match=r"goal .*outside the robust workspace.* mm away") as e:
        plan_query(port.cm, (0.0, 0.3), (0.06, 0.22), port.settings)
    # 0.06, 0.22 is about 10 mm right of the reachable region beside the port
    mm = float(str(e.value).rsplit(",", 1)[1].split("mm")[0])
    assert 2.0 < mm < 30.0


def test_start_where_no_gain_certifies(port):
    mf = port.mf
    bound = 1 - port.sc.planner.certify_margin
    bad = mf.valid & (mf.rho_star > bound + 0.005)
    cell = bad[:-1, :-1] & bad[1:, :-1] & bad[:-1, 1:] & bad[1:, 1:] & \
        mf.valid[:-1, :-1] & mf.valid[1:, :-1] & mf.valid[:-1, 1:] & mf.valid[1:, 1:]
    i, j = np.argwhere(cell)[len(np.argwhere(cell)) // 2]
    p = (mf.y[i] + 0.5 * port.cm.h, mf.z[j] + 0.5 * port.cm.h)
    with pytest.raises(InfeasibleError, match=r"start .*no gain can certify.*rho_star = [01]\.\d+ > 1 - certify_margin = 0\.98"):
        plan_query(port.cm, p, (0.0, 0.3), port.settings)


def test_disconnected_endpoints(port):
    mf = port.mf
    valid = mf.valid.copy()
    j = int(np.searchsorted(mf.z, 0.30))
    valid[:, j:j + 2] = False  # cut the workspace in two along z = 0.30
    cut = MetricField(mf.y, mf.z, valid, mf.G_norm, mf.phi_hat_max, mf.phi_max, mf.rho_star, mf.k_star, mf.meta)
    cm = CostMap(cut, "phi_hat_max", 1.0, True, 0.02)
    with pytest.raises(InfeasibleError, match="disconnected parts of the usable region"):
        plan_query(cm, (-0.1, 0.25), (-0.1, 0.35), port.settings)


def test_no_path_within_the_budget_is_an_error(port):
    # around the port the straight line is invalid; one iteration cannot find a path
    st = replace(port.settings, iterations=1)
    with pytest.raises(InfeasibleError, match="found no path .* within the budget"):
        plan_query(port.cm, (-0.04, 0.20), (0.05, 0.23), st, "around")


def test_planner_names(port):
    with pytest.raises(ErrplanError, match="expected one of .*BITstar"):
        plan_query(port.cm, (0.0, 0.4), (0.0, 0.3), replace(port.settings, planner="Nope"))
    with pytest.raises(ErrplanError, match="deadlock"):
        plan_query(port.cm, (0.0, 0.4), (0.0, 0.3), replace(port.settings, planner="PRMstar"))


def test_fields_without_rho_star_are_refused():
    sc = load_scenario(PORT)
    from errplan.fields import compute_fields

    mf = compute_fields(sc, 0.01, rho_star=False)
    with pytest.raises(ErrplanError, match="rho_star"):
        costmap_for(sc, mf)


# ----------------------------------------------------------------------------- refinement
def test_refine_never_raises_the_cost_and_keeps_validity(port):
    cm = port.cm
    ref = port.ref((-0.06, 0.40), (0.12, 0.40))
    rr = refine_path(cm, ref.path)
    assert cm.path_ok(rr.path) and rr.cost <= rr.cost_before
    zig = np.array([[-0.06, 0.40], [-0.03, 0.36], [0.0, 0.40], [0.05, 0.35], [0.12, 0.40]])
    assert cm.path_ok(zig)
    rr = refine_path(cm, zig)
    assert cm.path_ok(rr.path) and rr.cost < 0.95 * rr.cost_before
    assert rr.cost <= 1.05 * ref.cost


# ----------------------------------------------------------------------------- outputs
def test_plan_json_keys_and_cli(tmp_path, capsys):
    from errplan.cli import main

    out = tmp_path / "plan.json"
    assert main(["-q", "plan", str(PORT), "--json", str(out), "--query", "N-to-L", "--iterations", "3750"]) == 0
    text = capsys.readouterr().out
    assert "N-to-L" in text and "planned" in text and "direct" in text and "max ||G||" in text
    doc = json.loads(out.read_text())
    (q,) = doc["queries"]
    assert {"name", "start", "goal", "planned", "direct"} <= set(q)
    for P in (q["planned"], q["direct"]):
        assert {"path", "cost", "length", "max_G_norm", "max_phi_hat_max"} <= set(P)
        assert P["path"][0] == q["start"] and P["path"][-1] == q["goal"]
    assert q["name"] == "N-to-L" and q["start"] == [0.0, 0.415]


def _no_times(o):
    """A JSON document without its timings (every key naming a time)."""
    if isinstance(o, dict):
        return {k: _no_times(v) for k, v in o.items() if "time" not in k}
    return [_no_times(v) for v in o] if isinstance(o, list) else o


def test_plan_workers_give_the_same_plan_json(tmp_path, capsys):
    """``errplan plan --workers``: the fields' tiles and the queries' gains and simulations on 2 forked
    processes give the plan JSON and the tables of one process (only the times differ)."""
    from errplan.cli import main

    docs, texts = [], []
    for w in (1, 2):
        out = tmp_path / f"plan{w}.json"
        assert main(["-q", "plan", str(PORT), "--json", str(out), "--iterations", "3750", "--workers", str(w)]) == 0
        docs.append(json.loads(out.read_text()))
        texts.append([ln for ln in capsys.readouterr().out.splitlines() if "search" not in ln and "computed in" not in ln])
    assert len(docs[0]["queries"]) >= 2  # more than one query: they ran side by side
    assert _no_times(docs[0]) == _no_times(docs[1])
    assert texts[0] == texts[1]


def test_run_pipeline_workers_give_the_same_runs(port):
    """:func:`errplan.pipeline.run_pipeline` with ``workers=2`` (each query's gains, simulation and corner
    replays in a forked process): the same query JSONs, in the queries' order, and progress per query."""
    from errplan.pipeline import run_pipeline

    plan = plan_scenario(port.sc, port.mf)
    qs = [q.to_json() for q in plan.queries]
    one = run_pipeline(port.sc, qs, port.mf)
    seen = []
    two = run_pipeline(port.sc, [q.to_json() for q in plan.queries], port.mf, workers=2,
                       progress=lambda f, msg="": seen.append(f))
    assert [r.name for r in two["runs"]] == [q.name for q in plan.queries]
    assert _no_times(one["queries"]) == _no_times(two["queries"])
    assert seen[-1] == 1.0 and len(seen) == len(plan.queries)


def test_plan_refuses_bad_workers(capsys):
    from errplan.cli import main

    assert main(["plan", str(PORT), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--workers 0" in err


def test_unknown_query_lists_the_names(capsys):
    from errplan.cli import main

    assert main(["plan", str(PORT), "--query", "nope"]) == 2
    err = capsys.readouterr().err
    assert "'nope'" in err and "'N-to-L'" in err and "'across-deep'" in err


def test_plan_scenario_extra_keys_are_merged(port):
    plan = plan_scenario(port.sc, port.mf, query="N-to-L")
    qp = plan.queries[0]
    qp.extra["gains"] = [{"gain": 1.0}]
    assert plan.to_json()["queries"][0]["gains"] == [{"gain": 1.0}]


def test_same_seed_same_path(port):
    q = {q.name: q for q in port.sc.queries}["across-deep"]
    st = replace(port.settings, seed=5, refine=False)
    a = plan_query(port.cm, q.start, q.goal, st)
    b = plan_query(port.cm, q.start, q.goal, st)
    assert "time" not in (a.stopped_by, b.stopped_by)  # no time cap: the budget is counted
    assert np.array_equal(a.planned.path, b.planned.path)
    c = plan_query(port.cm, q.start, q.goal, replace(st, seed=6))
    assert not np.array_equal(a.planned.path, c.planned.path)
    # and with refinement (deterministic too)
    d = plan_query(port.cm, q.start, q.goal, replace(st, refine=True))
    e = plan_query(port.cm, q.start, q.goal, replace(st, refine=True))
    assert np.array_equal(d.planned.path, e.planned.path)


def test_a_slower_machine_plans_the_same_path(port, monkeypatch):
    """The iteration budget ends the search, not the clock: on a machine so slow that every reading of the
    clock is 10 s later than the last (so the test does not depend on this machine's speed or load), the
    plan is the same as here, to the bit. When the budget was a time, a busy second core was enough to
    change the bounded scenario's plan of this query."""
    import time

    q = {q.name: q for q in port.sc.queries}["across-deep"]
    st = port.settings
    assert st.time is None
    a = plan_query(port.cm, q.start, q.goal, st)
    now = [0.0]

    def ticking():
        now[0] += 10.0
        return now[0]

    monkeypatch.setattr(time, "perf_counter", ticking)
    b = plan_query(port.cm, q.start, q.goal, st)
    assert b.time_solve > 100.0  # the slow machine took minutes
    assert b.stopped_by == a.stopped_by == "iterations" and b.reproducible
    assert b.iterations == a.iterations == st.iteration_cap(2)
    assert b.refine_evaluations == a.refine_evaluations > 0
    assert np.array_equal(a.planned.path, b.planned.path)


def test_cost_recomputed_on_independent_finer_fields(port):
    """What an outside check does: recompute the returned path's cost with its own fields (here the
    scenario's fields computed again at 1 mm, integrated by dense sampling)."""
    from errplan.fields import compute_fields

    fine = compute_fields(port.sc, 0.001, rho_star=False)
    for q in port.sc.queries:
        qp = plan_query(port.cm, q.start, q.goal, port.settings, q.name)
        pts = np.concatenate([a + (b - a) * np.linspace(0, 1, 2001)[:, None]
                              for a, b in zip(qp.planned.path[:-1], qp.planned.path[1:])])
        f = 1.0 + fine.sample("phi_hat_max", pts)
        ds = np.hypot(*np.diff(pts, axis=0).T)
        ok = np.isfinite(f[1:]) & np.isfinite(f[:-1])
        assert ok.mean() > 0.999  # on the finer grid the path is inside the workspace too
        cost = float(np.sum(0.5 * (f[1:] + f[:-1])[ok] * ds[ok]))
        assert cost == pytest.approx(qp.planned.cost, rel=0.005), q.name


def test_degenerate_queries(port):
    """start == goal, a 10 nm query, and endpoints exactly on grid nodes."""
    qp = plan_query(port.cm, (0.0, 0.3), (0.0, 0.3), port.settings)
    assert qp.planned.valid and qp.planned.cost == 0 and qp.planned.length == 0
    assert qp.planned.max_G_norm == pytest.approx(float(port.mf.sample("G_norm", np.array([0.0, 0.3]))))
    qp = plan_query(port.cm, (0.0, 0.3), (0.0, 0.3 + 1e-8), port.settings)
    assert qp.planned.valid and 0 < qp.planned.cost < 1e-7
    y, z = port.mf.y, port.mf.z
    s, g = (float(y[120]), float(z[60])), (float(y[140]), float(z[100]))
    qp = plan_query(port.cm, s, g, port.settings)
    _check_plan(port, qp, port.ref(s, g))
