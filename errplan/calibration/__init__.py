"""Close the loop with measured data: residual -> missing effect -> model -> error before and after.

Pipeline (:func:`calibrate`):

1. **Replay with the declared model.** The declared model is the scenario's truth as it stands
   (arm, shaft, ``port.position``, the tip load of its error set closest to 0 — P2's scenarios
   fix one — and any ``[effects]`` it already declares). *Pose residual*: tracked
   tip minus the model's tracked tip at the encoder angles, every row at once; port friction's
   direction ``u`` for row t+1 is the motion the command of step t produced under the declared
   model, ``x_model(q(t+1)) - x_model(q(t))`` from two consecutive encoder rows of the run
   (:func:`motion_model`, :meth:`MeasuredData.commanded_directions`; docs/physics.md). *Trajectory
   residual*: the controller (:class:`errplan.simulation.ControllerModel`, at each run's gain)
   re-simulated noise-free on the model from each run's first encoder reading, step for step
   against the measured tracked tips, all runs batched. ``trajectory_rms_*`` covers each run's
   approach (steps 1 .. first arrival within ``max(0.5 mm, 4 noise floors)`` of the target: the
   paths P1 Fig. 8 compares), leaving out runs that diverge or cycle (see :func:`approach_mask`);
   the RMS over every step >= 1 of every run is reported beside it. After arrival the measured tip
   only jitters with the noise the controller chases, which a noise-free replay cannot predict
   (and a friction model makes the replay chatter there).
2. **Noise floor** (:func:`noise_floor`): the pose residual is fitted by a flexible smooth model
   — on compact clusters of rows (k-means of the model tip positions, 60-240 rows each) a
   quadratic or cubic Legendre polynomial (cluster size and degree by AIC) in the local tip
   position times ``[1, u_y, u_z]`` (``u`` friction's direction, so anything linear in the motion
   direction, like port friction, is smooth too) —
   and the noise floor is the degrees-of-freedom corrected RMS of what is left,
   ``sqrt(RSS / (2n - 2m))``. Every effect of the catalogue and the usual unmodelled ones (link
   lengths, scale errors) are smooth in the configuration, so what the local polynomials cannot
   follow is the measurement noise (tracker, plus encoder noise seen through the Jacobian).
   Fitted jointly with the polynomials, the row's motion (:func:`.noise.latency_features`: the model
   tip 1..5 median steps earlier minus now): a late tracker's residual follows the motion, not the
   pose. After the selection the same estimate on the selected model's residual; the noise floor
   is the smaller of the two (each is the noise plus what the flexible model cannot follow).
3. **Candidates** (:mod:`errplan.effects`): every effect alone, every pair, and the best pair
   plus each other effect; each fitted by nonlinear least squares on the pose residual, with
   ``s^2 (J^T J)^-1`` uncertainties and an identifiability check (unidentifiable combinations are
   not selectable and say why).
4. **Selection.** Among the selectable candidates (and "none") in order of BIC
   (``N ln(RSS/N) + p ln N``, ``N = 2n``), the first whose BIC and held-out pose error (folds of
   whole runs, seeded; each fold refitted from the full fit) are below those of every candidate
   with one effect fewer. Clean data select nothing; an effect that does not pay for its
   parameters on both counts is not added.
5. **Explained?** (:func:`.driver._verdict`, docs/physics.md "`explained` means explained"): only
   when (a) the selected model's residual is at most 1.25 noise floors, (b) the structure test
   (:func:`structure_test`: local polynomials and a global cubic of the tip with the row's motion,
   each fitted without some whole runs and scored on them) finds no significant structure, (c) no
   selected parameter is implausible and (d) a validation file's pose error after is below its
   error before and at most 1.25 noise floors. Otherwise the report names the failed conditions and
   the empirical last resort (:mod:`.empirical`) runs.

Outliers (:mod:`.outliers`: lone rows beyond 6 robust sigmas of the flexible fit's residual) and
dropouts are left out of every fit, the noise floor and every RMS, and listed.

All RMS values (pose, trajectory, noise floor) are **per coordinate**: the square root of the
mean over rows and over y, z of the squared residual. The noise floor therefore estimates the
tracker's sigma directly.

Layout (one module per concept): :mod:`.residual` (replay, pose and trajectory residuals),
:mod:`.noise` (noise floor, structure test), :mod:`.fit` (candidates fitted, held-out error, BIC),
:mod:`.selection`, :mod:`.report` (errors before/after, JSON, text), :mod:`.export` (the corrected
scenario), :mod:`.driver` (:func:`calibrate`) and :mod:`.design` (experiment design: the runs that
make the catalogue identifiable).
"""

from __future__ import annotations

from .driver import DEFAULT_FOLDS, calibrate
from .export import corrected_scenario_toml, to_toml
from .fit import Candidate, fit_candidate
from .noise import (FLEX_CONFIGS, STRUCTURE_P, STRUCTURE_RATIO, LocalBasis, NoiseFloor, Structure,
    kmeans_labels, noise_floor, structure_test)
from .report import TEXT_CANDIDATES, CalibrationReport, Errors
from .residual import (approach_mask, arrival_tolerance, check_against_model, declared_plant, motion_model,
    pose_residual, replay, rms, trajectory_errors)
from .selection import select

__all__ = ["calibrate", "CalibrationReport", "Candidate", "Errors", "NoiseFloor", "Structure", "LocalBasis",
           "approach_mask", "arrival_tolerance", "check_against_model", "declared_plant", "motion_model",
           "pose_residual", "replay", "rms", "trajectory_errors", "noise_floor", "structure_test", "kmeans_labels",
           "fit_candidate", "select", "to_toml", "corrected_scenario_toml", "DEFAULT_FOLDS", "STRUCTURE_P",
           "STRUCTURE_RATIO", "TEXT_CANDIDATES", "FLEX_CONFIGS"]
