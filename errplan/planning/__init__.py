"""Tip-path planning on the worst-case error fields, in OMPL's own terms (P1 Sec. IV), planar or spatial.

P1 Sec. IV: "a path planner could then trade off between indirect and direct paths". Here the
precomputed worst-case fields (:mod:`errplan.fields`) become the cost of an OMPL planning problem,
in the plane (``[y, z]``) or in space (``[x, y, z]``) with the same code. One module per concept:

- :mod:`~errplan.planning.costmap` -- :class:`CostMap`, the d-dimensional cost map: usable nodes
  (robust workspace, and ``rho_star <= 1 - certify_margin`` when certifiable), usable cells (all
  ``2**d`` corners usable), the exact segment integral of ``1 + weight * metric`` (multilinear in
  each cell) and segment validity through the cells a segment crosses, exact field maxima along
  paths, connected parts, one-line explanations of unusable points;
- :mod:`~errplan.planning.cellwalk` -- the compiled cell walk (Amanatides & Woo) behind it;
- :mod:`~errplan.planning.ompl_adapter` -- the only module importing ompl: the state space chosen by
  d, validity checker, exact motion validator, objective with an admissible heuristic, planner by
  name, the seeded search ending at its counted budget;
- :mod:`~errplan.planning.refine` -- :func:`refine_path`, shortcuts and coarse-to-fine vertex
  relaxation on the exact objective;
- :mod:`~errplan.planning.report` -- :class:`PathReport`, what a path is worth on the fields;
- :mod:`~errplan.planning.plan` -- :func:`plan_query`, :func:`plan_scenario` and their results
  (:class:`QueryPlan`, :class:`ScenarioPlan`, with ``to_json()`` giving the plan JSON of
  docs/interfaces.md; later steps add ``gains`` and ``simulation`` through :attr:`QueryPlan.extra`);
- :mod:`~errplan.planning.reference` -- the independent grid optimum every quality claim is a ratio
  to (Dijkstra on the grid with long moves, any d).

Numbers: coordinates and lengths in m; ``phi_*`` in rad; costs in m (a weighted length).
"""
from __future__ import annotations

from .costmap import METRIC_NAMES, CostMap
from .ompl_adapter import (DEFAULT_ITERATIONS, DEFAULT_ITERATIONS_SPATIAL, DEFAULT_PLANNER,
                           HEURISTIC_CALLS_PER_ITERATION, PLANNERS, default_iterations, make_objective,
                           make_space_information)
from .plan import (PlannerSettings, QueryPlan, ScenarioPlan, check_endpoints, costmap_for, fields_for_planning,
                   plan_query, plan_scenario, search_box, select_queries)
from .refine import REFINE_EVALUATIONS, RefineResult, refine_path
from .report import PathReport, path_report

__all__ = ["METRIC_NAMES", "PLANNERS", "DEFAULT_PLANNER", "DEFAULT_ITERATIONS", "DEFAULT_ITERATIONS_SPATIAL",
           "HEURISTIC_CALLS_PER_ITERATION", "REFINE_EVALUATIONS", "default_iterations", "CostMap", "PlannerSettings", "QueryPlan",
           "ScenarioPlan", "PathReport", "RefineResult", "check_endpoints", "costmap_for", "fields_for_planning",
           "make_objective", "make_space_information", "path_report", "plan_query", "plan_scenario",
           "refine_path", "search_box", "select_queries"]
