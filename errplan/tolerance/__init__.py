"""Tolerance-design queries: how much error a task can take, and where to put the port (P1 Sec. IV,
P2 Sec. IV-B and VI).

The size queries answer "the largest error of some kind for which the controller still converges
monotonically" (worst-case ``||G|| < 1``) and return a plot-ready curve; ``port_placement`` answers
"where should the port go so that the task is certifiably convergent over as much of the task
region as possible". Five kinds (``[[tolerance]]`` tables of a scenario, docs/interfaces.md):

``port``
    The largest port error ``e`` (m) such that, for every tip of a box region and every
    true port in ``estimate + S(e)``, the tip is reachable and ``||G||`` at the query's gain is
    below 1. ``S(e)`` is the segment ``[-e, e]`` along ``y`` or ``z`` (and ``x`` in 3-D), or the
    disk (planar) / ball (spatial) ``{|d| <= e}`` (``radial``). The controller is the scenario's
    (rigid lever through ``port.estimate``, or, in the plane, P2's flexion model fed by noisy end
    measurements, noise from ``[uncertainty] sensor_noise``).
``tip_load``
    The largest ``T`` (1/m^2) such that a *rigid-lever* controller through ``port.estimate`` keeps
    ``||G|| < 1`` over the region for every lateral tip load ``Ft/EI`` in ``[-T, T]`` (in 3-D:
    every lateral load of magnitude at most ``T``, the disc normal to the shaft) and every true port
    in the optional box ``estimate + [port_x x] port_y x port_z`` (without the box the true port is
    ``port.position``).
``insertion_band``
    P2's flexion-model controller (eqs. 4-14) fed by end positions and orientations with bounded
    noise: the worst case of ``||G||`` over the 6-D noise box as a function of insertion depth
    ``r/L``, the band where it stays below 1 and the best depth (P2 Fig. 7). Also the worst-case
    error of the estimated ``Fp/EI`` (P2 Fig. 8) and of the estimated port (P2 Fig. 9).
``tracker_noise``
    The largest tracker position noise ``s`` (m; angle noise ``angle_ratio * s / L`` rad) for
    which the worst-case ``||G||`` stays below 1 over a required insertion band.
``port_placement``
    For every nominal port on a candidate grid, the share of a task region that is robustly
    reachable with ``rho* <= 1 - certify_margin`` (``rho*`` as the fields compute it), the best
    port, and optionally a refined best port (:mod:`.placement`). Candidates run as independent
    tasks on local worker processes or a dask cluster.

All kinds run on planar and spatial scenarios. In 3-D ``insertion_band`` and ``tracker_noise`` take
loads of the given magnitude in every direction normal to the shaft and the tracker's 3-D noise set
(positions per coordinate, directions within a cone), the shaft along ``shaft_direction``
(:class:`SpatialInsertionModel`); their worst case is searched (corners and a pattern search), a
lower bound, and the JSON says so (``lower_bound``).

Soundness. Each criterion is a worst case over a *nested* family of sets (segments, disks, load
ranges, noise boxes that grow with the error size), hence monotone in the size; the size is found
per tip (or per depth) by bisection, and the answer is the minimum over the region (or band).
The worst case over each set is found by dense sampling plus a local pattern search; for the
6-D noise box, by all 64 vertices plus a pattern search from the worst vertex (``||G||`` is close
to a convex function of small noise, so its maximum sits at a vertex; the tests compare with
scipy multi-start optimisation and 20,000 random draws). Where the box also holds noise vectors
that make P2's estimate degenerate (estimated ``a`` outside ``(0, L)``: a thin interior set the
vertices can miss, with ``||G|| >= 1`` in its limit), the worst case is reported as at least 1.
Region grids are refined (nested, spacing halved) until the answer changes by less than 1%
(reported as ``refinement_change``).

Layout: :mod:`.result` (the answer object), :mod:`.search` (bisection, box worst cases),
:mod:`.insertion` (P2's insertion-depth queries), :mod:`.region` (``port`` and ``tip_load`` over a
region, planar and spatial), :mod:`.placement` (``port_placement``), :mod:`.run` (dispatch and the
size checks done before any query runs).
"""
from __future__ import annotations

from .insertion import (HOLDS, LIBERTY_ANGLE_RATIO, InsertionModel, SpatialInsertionModel, flexed_jacobian_hold,
                        insertion_band, insertion_worst, spatial_insertion_band, spatial_tracker_noise, tracker_noise)
from .placement import MAX_CANDIDATES, candidate_scenario, port_placement, rank_key, score
from .region import port_tolerance, region_grid, tip_load_tolerance
from .result import Progress, ToleranceResult
from .run import PLANAR_KINDS, check_sizes, run_all, run_query
from .search import box_worst

__all__ = ["ToleranceResult", "Progress", "run_all", "run_query", "check_sizes", "port_tolerance",
           "tip_load_tolerance", "port_placement", "insertion_band", "insertion_worst", "tracker_noise",
           "InsertionModel", "flexed_jacobian_hold", "box_worst", "region_grid", "HOLDS", "LIBERTY_ANGLE_RATIO",
           "MAX_CANDIDATES", "PLANAR_KINDS", "candidate_scenario", "rank_key", "score", "SpatialInsertionModel",
           "spatial_insertion_band", "spatial_tracker_noise"]
