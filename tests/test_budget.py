"""The planner's budgets are counted, not timed: ``[planner] iterations`` ends the search and the
refinement has its own count of segment evaluations, so a seeded plan is the same on every machine,
loaded or not; ``time`` is only a safety cap, and a plan it cuts says so (``stopped_by`` "time", a
line in the table, ``reproducible`` false in the JSON)."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest

from conftest import SCENARIOS, write_scenario
from errplan import api
from errplan.cli import main
from errplan.errors import ErrplanError
from errplan.planning import PlannerSettings, costmap_for, fields_for_planning, plan_query, plan_scenario
from errplan.planning import cellwalk, refine as refine_mod
from errplan.planning.refine import REFINE_EVALUATIONS, refine_path

PORT = SCENARIOS / "beasley2004_port.toml"


class _P:
    def __init__(self):
        self.sc = api.load_scenario(PORT)
        self.mf = fields_for_planning(self.sc, 0.004, workers=1)
        self.cm = costmap_for(self.sc, self.mf)
        self.q = {q.name: q for q in self.sc.queries}["across-deep"]  # a detour pays off: the search matters
        self.settings = replace(PlannerSettings.from_model(self.sc), iterations=3000)


@pytest.fixture(scope="module")
def P():
    return _P()


def _ticking(monkeypatch, step: float = 10.0):
    """A machine so slow that every reading of the clock is ``step`` s later than the last."""
    now = [0.0]

    def ticking():
        now[0] += step
        return now[0]

    monkeypatch.setattr(time, "perf_counter", ticking)


# ----------------------------------------------------------------------------- the scenario's keys
def test_iterations_is_the_budget_and_time_only_a_cap(tmp_path):
    sc = api.load_scenario(write_scenario(tmp_path, planner={"iterations": 1234, "time": None}))
    assert sc.planner.iterations == 1234 and sc.planner.time is None
    st = PlannerSettings.from_model(sc)
    assert st.iteration_cap(2) == 1234 and st.time is None
    # an old scenario's time = 1.0 is kept as the cap; without iterations the planner's default budget
    old = api.load_scenario(write_scenario(tmp_path, planner={"iterations": None, "time": 1.0}, name="old.toml"))
    st = PlannerSettings.from_model(old)
    assert st.time == 1.0 and st.iterations is None and st.iteration_cap(2) == 187  # RRTstar's, planar
    assert PlannerSettings(planner="BITstar").iteration_cap(2) == 7500
    assert PlannerSettings(planner="BITstar").iteration_cap(3) == 3750
    # the command line overrides both
    assert PlannerSettings.from_model(sc, iterations=99, time=2.5).iteration_cap(2) == 99


@pytest.mark.parametrize("bad", [0, -5, 1.5, True, "many", 10**12])
def test_bad_iterations_is_one_clear_error(tmp_path, capsys, bad):
    src = write_scenario(tmp_path, planner={"iterations": bad})
    assert main(["-q", "plan", str(src), "--json", str(tmp_path / "p.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[planner] iterations" in err and "integer" in err, err
    assert not (tmp_path / "p.json").exists()


@pytest.mark.parametrize("bad", ["0", "-3", "2.5", "x"])
def test_bad_iterations_option_is_one_clear_error(tmp_path, capsys, bad):
    src = write_scenario(tmp_path)
    with pytest.raises(SystemExit) as e:  # a usage error: argparse's exit, one line
        main(["-q", "plan", str(src), "--iterations", bad])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--iterations" in err and repr(bad) in err, err


def test_settings_refuse_bad_budgets():
    for kw in ({"iterations": 0}, {"iterations": 2.0}, {"iterations": False}, {"time": 0.0},
               {"time": float("nan")}, {"refine_evaluations": -1}):
        with pytest.raises(ErrplanError, match=next(iter(kw))):
            PlannerSettings(**kw).check()


# ----------------------------------------------------------------------------- counted, not timed
def test_a_busy_core_does_not_change_the_plan(P):
    """The same seeded query planned on a quiet machine and while another process keeps a core busy:
    the same path, to the bit, and the same counts."""
    a = plan_query(P.cm, P.q.start, P.q.goal, P.settings, "q")
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        b = plan_query(P.cm, P.q.start, P.q.goal, P.settings, "q")
    finally:
        burner.kill()
        burner.wait()
    assert a.stopped_by == b.stopped_by == "iterations" and a.reproducible and b.reproducible
    assert a.iterations == b.iterations == 3000
    assert a.refine_evaluations == b.refine_evaluations > 0
    assert np.array_equal(a.planned.path, b.planned.path)
    assert json.dumps(a.to_json(timing=False)) == json.dumps(b.to_json(timing=False))


def test_the_time_cap_cuts_and_says_so(P, monkeypatch):
    """A cap the clock passes (here a machine where each clock reading is 10 s later than the last):
    the search ends by time, the plan says it is not reproducible, in the JSON and in the table."""
    from errplan.cli.plan import plan_table

    _ticking(monkeypatch, 0.001)  # tens of readings per iteration: the cap passes after its first solution
    st = replace(P.settings, time=30.0)
    plan = plan_scenario(P.sc, P.mf, query="across-deep", settings=st)
    (q,) = plan.queries
    assert q.stopped_by == "time" and not q.reproducible and 0 < q.iterations < 3000
    j = plan.to_json(timing=False)["queries"][0]["search"]
    assert j["stopped_by"] == "time" and j["reproducible"] is False and j["time_cap"] == 30.0
    text = plan_table(plan)
    assert "across-deep: stopped by the time cap (30 s)" in text and "not reproducible on another machine" in text
    q.stopped_by, q.refine_stopped_by, q.refine_evaluations = "iterations", "time", 12  # a cut refinement alone
    assert not q.reproducible and plan.to_json()["queries"][0]["search"]["reproducible"] is False
    assert "across-deep: refinement stopped by the time cap (30 s) after 12 evaluations" in plan_table(plan)
    # without the cap the same slow machine plans to the end of the budget, and the table has no such line
    plan = plan_scenario(P.sc, P.mf, query="across-deep", settings=replace(st, time=None))
    assert plan.queries[0].stopped_by == "iterations" and "not reproducible" not in plan_table(plan)


def test_a_tiny_time_cap_on_the_command_line(tmp_path, capsys):
    src = write_scenario(tmp_path)
    out = tmp_path / "p.json"
    assert main(["-q", "plan", str(src), "--json", str(out), "--time", "1e-9"]) == 0
    text = capsys.readouterr().out
    (q,) = json.loads(out.read_text())["queries"]
    assert q["search"]["stopped_by"] == "time" and q["search"]["reproducible"] is False
    assert "time cap 1e-09 s" in text and "not reproducible on another machine" in text


# ----------------------------------------------------------------------------- the refinement's budget
def _rough(P):
    """A valid but poor path of the query: the first solution of a short search, unrefined."""
    qp = plan_query(P.cm, P.q.start, P.q.goal, replace(P.settings, iterations=300, refine=False), "q")
    return qp.planned.path


def test_refinement_counts_its_evaluations(P, monkeypatch):
    """Every segment evaluation the refinement spends is one call of the compiled cell walk with its
    validity check (counted here independently, by wrapping the walk); a budget stops it exactly there,
    keeping every change made so far (valid, never dearer); no budget left is the input path."""
    path = _rough(P)
    calls = [0]
    real = cellwalk.walk2

    def counted(D, y0, z0, y1, z1, check, cost):
        calls[0] += bool(check)
        return real(D, y0, z0, y1, z1, check, cost)

    monkeypatch.setattr(cellwalk, "walk2", counted)
    full = refine_path(P.cm, path)
    assert full.stopped_by == "converged" and calls[0] == full.evaluations and 0 < full.evaluations < REFINE_EVALUATIONS
    assert full.cost < full.cost_before
    for n in (0, 1, 57, full.evaluations // 3):
        calls[0] = 0
        r = refine_path(P.cm, path, evaluations=n)
        assert r.stopped_by == "evaluations" and r.evaluations == calls[0] == n
        assert P.cm.path_ok(r.path) and r.cost <= r.cost_before
        assert r.cost >= full.cost * (1 - 1e-9)  # a prefix of the full refinement's (cost-lowering) changes
    assert np.array_equal(refine_path(P.cm, path, evaluations=0).path, np.asarray(path, float))
    # exactly enough: the same result as no budget
    again = refine_path(P.cm, path, evaluations=full.evaluations)
    assert again.stopped_by == "converged" and np.array_equal(again.path, full.path)


def test_refinement_ignores_the_clock_without_a_cap(P, monkeypatch):
    path = _rough(P)
    quiet = refine_path(P.cm, path)
    _ticking(monkeypatch)
    slow = refine_path(P.cm, path)
    assert slow.stopped_by == "converged" and slow.evaluations == quiet.evaluations
    assert np.array_equal(slow.path, quiet.path)
    cut = refine_path(P.cm, path, deadline=time.perf_counter() + 50.0)  # a cap the slow machine passes
    assert cut.stopped_by == "time" and cut.evaluations < quiet.evaluations and P.cm.path_ok(cut.path)
    assert refine_mod.REFINE_EVALUATIONS == REFINE_EVALUATIONS


def test_arm_checks_have_their_own_share_of_the_refinement():
    """With arm checks (tens of ms per motion against a microsecond per cell walk) the refinement's
    clearance checks are counted in its budget and capped by their own share; without them, only the budget."""
    from types import SimpleNamespace

    seen = []
    stub = SimpleNamespace(_clear=lambda *xyz: seen.append(xyz) or True, arm_checks=object())
    count = refine_mod._Counter(10, None, 3)
    clear = refine_mod._clear_fn(stub, count)
    for k in range(3):
        assert clear([0.0, 0.0, k], [1.0, 0.0, k])
    with pytest.raises(refine_mod._Budget):
        clear([0.0, 0.0, 9.0], [1.0, 0.0, 9.0])
    assert count.why == "arm checks" and count.checks == count.n == len(seen) == 3
    plain = refine_mod._Counter(5, None, 3)  # the anatomy's checks alone: only the budget counts them
    clear = refine_mod._clear_fn(SimpleNamespace(_clear=lambda *xyz: True), plain)
    for _ in range(5):
        clear([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    with pytest.raises(refine_mod._Budget):
        clear([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    assert plain.why == "evaluations" and plain.n == 5 and plain.checks == 0


@pytest.mark.parametrize("bad", [0, -1.0, "long", True])
def test_bad_time_cap_is_one_clear_error(tmp_path, capsys, bad):
    src = write_scenario(tmp_path, planner={"time": bad})
    assert main(["-q", "plan", str(src)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[planner] time" in err, err
