"""Compiled field kernels (numba): the worst case of ``||I - k J Jhat^-1||``, ``|phi_max|`` and
``rho*`` over a bounded error set, tip by tip, for the planar arm (``d = 2``, closed forms through
conformal parts) and for any URDF arm (``d = 3``).

One search serves both dimensions; only the physics of one error instance (:func:`_instance2`, :func:`_instance3`)
branches on ``d``. The search is the method of :mod:`errplan.fields` (the numpy reference in
:mod:`.search`): the error box sampled on a grid, the worst sample refined by a coordinate
pattern search (step halved ``refine`` times, polls a box face clips skipped, further passes while
the worst case still climbs), and a second local maximum of the sample grid refined as well when
it could overtake the first. A tip is valid only if every evaluated instance reaches it.

Straight-shaft (unloaded) instances are also computed in bulk, many per vectorized loop
(:func:`_levers2`, :func:`_levers3`): a tip's samples at once, and, where no load axis is active, the
polls of many tips' worst-||G|| refinements at once (:func:`_pattern_lanes`). Same arithmetic, same
answers to the last bit, a fraction of the time.

Under a load (3-D), ``||I - k M||`` costs a 3 x 3 sigma_max; the search computes it only where a comparison
needs it. A tight upper bound (:func:`_gnorm_below`: Laguerre steps down the characteristic cubic of
``G^T G``, each checked) settles most comparisons: the sampled values while the starts are chosen
(:func:`_starts_lazy`), the polls of the pattern search, rho*'s golden section and its certification at
k* (which also reuse the values already computed at the scenario gain and at k*). A sample or poll is
skipped only where its bound shows it cannot change a maximum nor which instance attains it: the same
results to the last bit.

Error parameters ``theta``: planar ``(dy, dz, t)`` (port offset, lateral tip load over EI in the
shaft frame, signed); spatial ``(dx, dy, dz, tau, psi)`` (port offset, lateral load magnitude and
its direction angle around the port->tip line, periodic). Compiled once and cached on disk
(``cache=True``): later runs pay no compile cost.

The package, imports pointing down: :mod:`.reach` (the planar arm's exact reachability test, the
certificates of a tip's wrists), :mod:`.instance` (the physics of one error instance: levers and
flexed shafts), :mod:`.metrics` (``||I - k M||``, ``|phi_max|`` of a map), :mod:`.search` (pattern search,
golden section) and :mod:`.loops` (the entry loops Python calls). Every name is importable from here.
:mod:`.flexion` and :mod:`.effects` (the exact effects path's ``M = R J Jhat^-1``) serve the numpy search
(:mod:`errplan.fields.search`) and are imported where used.
"""
from __future__ import annotations

from .reach import _arc_class, _cos_beta, _planar_reachable, _tip_reach, _tip_reach2, planar_arm_params
from .instance import (NEWTON, RCOND, _compose2, _corners_out2, _est_inverse2, _flexed_J3, _flexed_parts2, _gnorm2,
                       _gval_block, _instance2, _instance3, _lever3, _lever_block3, _lever_J, _lever_out, _levers2,
                       _levers3, _perp_basis, _solve_b, _straight2)
from .metrics import _phimax, gnorm, gval, phi_bound, phimax
from .search import (LANE_TIPS, _climbing, _far, _golden, _gnorm_below, _golden_gain, _gval_skip, _gval_ub, _gval_ub_at, _local_max, _neighbour, _pattern, _pattern_g,
                     _pattern_lanes, _peak_raise, _poll_coord, _poll_value, _rho_final, _sample_table)
from .loops import (_LANE_TILES, _TILES, _WANT_PHI, _Lanes, _lanes_tile, _starts_lazy, _maps2, _maps3, _motion_maps, _per_dim,
                    _search, _tile2, _tile2g, _tile3, _tile3g, load_lanes, motion_maps, run_lanes, worst_case_tile)
