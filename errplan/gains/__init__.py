"""Certified per-segment gains (casadi) for a planned tip path: the convergence-ball certificate.

One module per concept, imports pointing down: :mod:`.options` (settings and results) <- :mod:`.physics`
(ball samples, per-pair ||G||, the 3-D model, one nonlinear step) <- :mod:`.certificate` (a ball's
sample, rho(k), scans, pruning) <- :mod:`.solve` (the casadi problem, the only casadi import) and
:mod:`.verify` (one verification for the plane and 3-D) <- :mod:`.schedule` (:func:`schedule_gains`).

The controller drives the tip through the path's waypoints; on segment ``s`` (from ``a`` to ``b``)
it aims at ``b``. While the error length ``|x - b|`` shrinks, the tip stays inside the ball
``B_s`` of centre ``b`` and radius ``R_s = |b - a| + switch_tolerance`` (the controller switches to
``b`` once it is within ``switch_tolerance`` of ``a``). So the segment converges monotonically
whatever the truth inside the error set is when, at every tip ``x`` of ``B_s`` that the truth
``theta`` can reach, ``||G|| = ||I - k J Jhat^-1|| < 1`` (P1 Sec. II-B, by induction on the steps).

With the conformal parts ``(mu, nu)`` of ``M = J Jhat^-1`` (:mod:`errplan.metrics`),
``||G(k)|| = |1 - k mu| + k |nu|``: convex in ``k``, so ``rho_s(k) = max over (x, theta) in B_s``
is convex too and the gains of all segments are chosen together as one casadi/IPOPT problem:

    minimise   sum_s log(R_s / tol_s) / (-log r_s)          (predicted steps, P1 eq. 6)
               + W sum_s sigma_s                             (gain-change slack)
    subject to r_s >= |1 - k_s mu_i| + k_s |nu_i|            for the sampled pairs i of B_s
               r_s <= 1 - margin                             (every certifiable segment)
               |k_{s+1} - k_s| <= max_gain_change + sigma_s, sigma_s >= 0.

The epigraph constraint is written without a square root (a second-order cone in smooth form):
``(r - k |nu|)^2 >= (1 - k Re mu)^2 + (k Im mu)^2`` and ``r - k |nu| >= 0``. Sampled pairs
that never attain the maximum on a fine numpy grid of ``k`` are pruned before the solve (grids
belong to numpy, optimisation to casadi).

A segment whose ball is too large to certify (sampled ``rho* > 1 - margin``) is halved, up to
``max_depth`` times. After the solve every certificate is verified on a denser sample than the
optimiser used (more tips, boundary ring, more error-set samples, local refinement of the worst
instance and of the worst tip), and the verified worst case is what ``certified_G_norm`` reports.
The verification also replays one controller step from every sampled (tip, instance) pair with
the full nonlinear kinematics (``step_ratio = |x' - b| / |x - b|``): the ``||G||`` argument is
first order, the replay is not. A segment is ``certified`` only if both are below 1; one that no
gain certifies is reported with ``certified = false`` and the reason.

**3-D** (docs/physics.md "Spatial robots"; the same routine, :class:`SpatialModel` for the physics).
Balls are 3-D (centre, a Fibonacci-spiral volume sample, a Fibonacci sphere), the error set is
(port box, lateral load magnitude and direction), ``M = J Jhat^-1`` is 3 x 3 from the compiled
kernels (:class:`errplan.fields.KernelEvaluator`) and ``||G(k)|| = sigma_max(I - k M)``. For a unit
direction ``v``, ``||(I - k M) v||^2 = (1 - k a)^2 + (k b)^2`` with ``a = v.Mv`` and
``b = |Mv - a v|``: the planar cone constraint with ``|nu| = 0``. ``sigma_max`` is the maximum of
these over ``v``, so the casadi problem is the planar one over *cuts* ``(M_i, v)``; it starts with
the right singular vectors at a few gains of the numpy grid and, after each solve, adds the
singular vector of ``I - k_s M_i`` at the solved gain wherever the cuts underestimate the exact
``sigma_max`` (cutting planes, until the cuts are exact at the solution to 1e-9). Pairs are
pruned on a compiled k-grid as in the plane. A ball is only certified when the controller's
Jacobian cannot be singular in it: ``|x - estimate| > 2 delta + L atan(tau_max L^2/12)`` at every
tip (``delta`` the port box's largest distance from the estimate; analytic, see
:meth:`SpatialModel.singular_free`). Sample sizes differ (``GainOptions.for_dim(3)``): 2 samples per
uncertain port/load axis and 8 load directions for the optimiser, 3 and 8 plus the same pattern
searches for the verification; the nonlinear one-step replay runs from every verification tip
under every corner instance (port corners x {no load, the largest load in 4 directions}) and at
the refined worst pairs.

The truth's ``[effects]`` (docs/physics.md "From measured data to the plan"): every pair takes the truth's
``J`` (its arm's geometry, instrument length, port, joint offsets, sag, load) at the encoder angles that put
the true tip there and the declared controller's ``Jhat`` at the same angles; with a tracker registration
the loop closes on the tracked tip ``R x + b``, so the ball is drawn in the tracker's frame (its tips mapped
to the true tips ``R^-1 (y - b)``) and the certificate bounds ``||I - k R J Jhat^-1||``; the one-step replay
runs the truth (:meth:`errplan.fields.Evaluator.effect_step_ratio`, :class:`.physics.EffectsKernel`). Effects
the metrics cannot express (:func:`errplan.errorset.uncovered_effects`) are not in the certificate.

P2's flexion controller in 3-D (:class:`errplan.gains.physics.FlexionKernel`): the motion maps
come from :class:`errplan.fields.SpatialFlexionEvaluator` (compiled) with an axis of noise corners,
flattened into the sample; the one-step replay takes the worst corner; a ball is singular-free when
it keeps ``delta + deviation + 2 e_p`` from every true port, ``e_p`` the largest estimated-port
error over the noise corners at the ball's centre (sampled, not analytic as for the lever).
"""
from __future__ import annotations

from .certificate import rho_of_k, rho_of_k_M
from .options import GainOptions, GainSchedule, Segment
from .physics import SpatialModel, ball_tips, cut_rows, gnorm3_grid, perp_basis, sphere_points, step_ratio
from .schedule import cut_path, options_from_scenario, schedule_gains, single_segment
from .solve import solve_gains
from .verify import verify_segment

__all__ = ["GainOptions", "GainSchedule", "Segment", "SpatialModel", "ball_tips", "sphere_points", "cut_rows",
           "gnorm3_grid", "perp_basis", "step_ratio", "rho_of_k", "rho_of_k_M", "solve_gains", "verify_segment",
           "cut_path", "options_from_scenario", "schedule_gains", "single_segment"]
