"""Compiled small-matrix kernels (numba) for the metrics of 2x2 and 3x3 motion maps.

One module per concept, imports pointing down: :mod:`.basics` (decorator, scaling, inverses) <-
:mod:`.eigen` (symmetric 3x3 eigenproblems) <- :mod:`.singular` (sigma_max, ||I - k M||, v_sigma) <-
:mod:`.phimax` (exact |phi_max|, p_phi) <- :mod:`.gain` (rho*) <- :mod:`.batch` (loops over stacks).

Every kernel is ``@njit(cache=True, fastmath=False, error_model="numpy")`` and allocates nothing:
it takes matrices (2-D arrays or views such as ``M[i]``) and either returns scalars or writes into
a caller-provided output array, so field kernels can call them from their own compiled loops
hundreds of millions of times. Results are floats; a non-finite input matrix gives NaN (never an
exception, never inf), except where a docstring says otherwise.

Public kernels (shapes in brackets):

- ``inv2(A[2,2], out[2,2]) -> det``, ``inv3(A[3,3], out[3,3]) -> det``: adjugate / cofactor
  inverse. ``out`` is NaN where ``det == 0``; the caller decides singularity with
  ``singular2(A, det, rcond)`` / ``singular3(A, det, rcond)``: True when
  ``|det| <= rcond * ||A||_F^d`` (or ``det`` is not finite), the test ``metrics.inv`` uses.
- ``matmul3(A, B, out)``: ``out = A @ B`` (``out`` must not alias ``A`` or ``B``).
- ``sigma_max2(A)``, ``sigma_max3(A)``: largest singular value; ``g_norm2(M, k)``,
  ``g_norm3(M, k)``: ``||I - k M||_2``.
- ``phi_max2(M)``, ``phi_max3(M)``: exact ``|phi_max| = max over unit v of angle(v, M v)`` (rad),
  ``pi`` when ``M`` has a real eigenvalue ``<= 0`` (a direction reversed or annihilated).
- ``p_phi3(M, out3)``: a unit direction attaining ``phi_max3`` (up to sign); returns its angle.
- ``v_sigma3(G, out3)``: right singular vector of the largest singular value; returns sigma_max.
- ``min_over_gain3(Ms[m',3,3], m, out[2])``: ``rho* = min over k > 0 of max_i ||I - k Ms[i]||``
  over the first ``m`` matrices, ``out = [rho*, k*]``.

How ``phi_max3`` is exact (docs/fields.md, "Exact |phi_max| in 3-D"): with ``S = (M + M^T)/2``,
``A = M^T M``, the cosine of the angle of ``v`` is ``a / sqrt(b)``, ``(a, b) = (v^T S v, v^T A v)``
on the unit sphere, and the set ``W`` of such pairs is convex (Brickman). If ``S >= 0`` every
angle is acute and ``cos phi_max = 2 sqrt(max_{s>0} s lambda_min(S - s A))``, a concave 1-D
maximisation (strong duality). Otherwise ``cos phi_max = -2 max_y psi(y)`` with
``psi(y) = tau lambda_max(-S, tau^2 I + A)``, ``tau = e^y``: a 1-D search over
``y in [ln sigma_min, ln sigma_max]`` whose stationary points are the roots of
``F(y) = ln |M x(y)| - y`` (``x(y)`` the generalised eigenvector); ``F`` falls with slope at most
1, which bounds where the maxima can hide.

Symmetric 3x3 eigenproblems use the trigonometric closed form, then deflate: the eigenvector of
the best-separated eigenvalue from cross products, the other two from the 2x2 restriction to its
orthogonal complement (a stable closed form). This keeps eigenvalues accurate to rounding
of ``||H||`` where the bare trigonometric formula loses half the digits (near-double eigenvalues).
"""
from __future__ import annotations

from .basics import _jit, _maxabs9, _maxabs3x3, inv2, inv3, singular2, singular3, matmul3, PI, NAN  # noqa: F401
from .eigen import _sym3_trig, _sym3_eigvals, _cross_null, _complement, _qform, _eig2, _sym2_in_plane, _sym3_eigh, _sym3_top, _sym3_max, SQRT3  # noqa: F401
from .singular import _smax2, sigma_max2, _smax3, sigma_max3, g_norm2, g_norm3, v_sigma3  # noqa: F401
from .phimax import phi_max2, _angle, _cubic_root_in, _reversal, _acute_eval, _rq, _quad_lower, _model_step, _acute, _psi_eval, _skip, _refine, _obtuse, _phi_max3, phi_max3, p_phi3, ACUTE_RTOL, OBTUSE_STEP  # noqa: F401
from .gain import _max_gnorm3, min_over_gain3  # noqa: F401
from .batch import _inv3_many, _g_norm3_many, _sigma_max3_many, _phi_max3_many, _p_phi3_many, _v_sigma3_many, _min_over_gain3_many  # noqa: F401
