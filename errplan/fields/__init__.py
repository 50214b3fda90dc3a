"""Worst-case metric fields over a tip grid and a bounded error set (P1 Sec. IV, P2 Sec. IV-B).

For every tip position ``x`` of a grid and every error instance (true port = estimate + offset,
tip load ``t = Ft/EI``), the *true* configuration is the one that puts the true tip at ``x``
(:func:`errplan.kinematics.shaft.flexed_wrist`), the true Jacobian ``J`` is the flexed-shaft
Jacobian there and the controller's ``Jhat`` comes from its model (rigid lever through the port
estimate, or P2's flexion model fed by the measured end poses, worst case over the corners of the
sensor-noise box). Because ``J Jhat^-1 = J_tw Jhat_tw^-1`` (the arm Jacobian cancels), metrics
depend on the arm only through reachability.

The worst case over the continuous error set is found by sampling it on a grid
(``[uncertainty] samples`` per axis) and refining each tip's worst sample by a local pattern
search (step halved ``REFINE_LEVELS`` times; polls that a box face clips are skipped; up to
``EXTRA_PASSES`` further passes where the worst case still climbs, e.g. along a ridge). Where a
second sampled local maximum could overtake the first after refinement (its value plus twice
its parabolic refinement gain comes within ``SECOND_START`` of the worst), it is refined too.
Checked against an independent dense-sampling implementation (tests/test_fields.py): it never
falls below the dense worst case by more than 1e-3 (relative above 1). A tip is in the workspace
only if it is reachable under every instance evaluated (robust validity).
"""
from __future__ import annotations

from .compute import ALL_METRICS, DEFAULT_METRICS, KernelEvaluator, compute_fields, parse_metrics, tip_grid, workspace_bounds
from ..errorset import ErrorSet, error_set
from .evaluator import EFFECT_NEWTON_ITERS, JACOBIAN_EFFECTS, Evaluator, SpatialFlexionEvaluator
from .grid import METRIC_NAMES, MetricField
from .search import EXTRA_PASSES, REFINE_LEVELS, SECOND_START, Progress, minimize_gain, worst_case

__all__ = ["ErrorSet", "Evaluator", "MetricField", "compute_fields", "minimize_gain", "worst_case",
           "workspace_bounds", "REFINE_LEVELS", "EXTRA_PASSES", "SECOND_START", "EFFECT_NEWTON_ITERS",
           "JACOBIAN_EFFECTS", "Progress", "ALL_METRICS", "DEFAULT_METRICS", "METRIC_NAMES", "error_set",
           "parse_metrics", "tip_grid", "KernelEvaluator", "SpatialFlexionEvaluator"]
