"""Kinematic-error metrics of P1 Sec. II-B for planar (2x2) and spatial (3x3) motion maps.

Every public function takes matrices of shape ``(..., d, d)`` and vectors ``(..., d)`` with
``d = 2`` or ``3``; leading axes are batch axes (numpy gufunc style). ``M = J Jhat^-1`` is the
actual motion per desired motion at unit gain and ``G = I - k M`` (P1 eq. 5).

**Plane (d = 2): closed forms.** Every 2x2 real matrix acts on ``v = [v0, v1]`` like
``z -> mu z + nu conj(z)`` on the complex number ``z = v0 + i v1``, with the *conformal* part
``mu = (M00 + M11)/2 + i (M10 - M01)/2`` and the *anticonformal* part
``nu = (M00 - M11)/2 + i (M01 + M10)/2``. Then

- the singular values are ``|mu| + |nu|`` and ``||mu| - |nu||``, so for the motion map
  ``M = J Jhat^-1`` and ``G = I - k M``: ``||G|| = |1 - k mu| + k |nu|`` (P1 eq. 6);
- the actual motion for a desired unit motion ``e^{is}`` is ``e^{is} (mu + nu e^{-2is})``: its
  angle to the desired motion runs over ``arg`` of a circle of centre ``mu`` and radius ``|nu|``,
  so ``|phi_max| = min(pi, |arg mu| + asin(|nu|/|mu|))`` when ``|nu| < |mu|`` and ``pi``
  otherwise (P1 eq. 9, which the paper only searched numerically).

**Space (d = 3): compiled kernels** of :mod:`errplan.linalg` (closed-form ``sigma_max`` of a 3x3
matrix; exact ``|phi_max|`` by a 1-D dual search, docs/fields.md "Exact |phi_max| in 3-D").
The planar results are those of the closed forms above, bit for bit; 2x2 input never goes
through the 3-D kernels.

Singular and non-finite input: :func:`inv` (and :func:`motion_map`) return NaN exactly where
their ``singular`` mask is True. ``|phi_max|`` is ``pi`` for a singular ``M`` (an annihilated
motion counts as the worst). In 3-D a matrix with a non-finite entry gives NaN from every metric
(and counts as ``M = 0`` in :func:`min_over_gain`, forcing ``rho* = 1``); in the plane the closed forms keep their historical
results (NaN norms, ``phi_max = pi``).
"""
from __future__ import annotations

import math

import numpy as np


def _dim(A: np.ndarray, what: str = "matrices") -> int:
    """``d`` of ``(..., d, d)`` matrices, 2 or 3; a ``ValueError`` naming the shape otherwise."""
    shp = np.shape(A)
    if len(shp) < 2 or shp[-1] != shp[-2] or shp[-1] not in (2, 3):
        raise ValueError(f"{what} must have shape (..., d, d) with d = 2 or 3, got {shp}")
    return shp[-1]


def _vec_dim(v: np.ndarray, d: int, what: str = "vectors") -> None:
    shp = np.shape(v)
    if len(shp) < 1 or shp[-1] != d:
        raise ValueError(f"{what} must have shape (..., {d}) to match {d}x{d} matrices, got {shp}")


def _linalg():
    """The compiled kernels, imported on first 3-D use (planar callers never load numba)."""
    from . import linalg
    return linalg


def _flat(A: np.ndarray, tail: tuple[int, ...]) -> np.ndarray:
    """C-contiguous float64 ``(n, *tail)`` view/copy of ``(..., *tail)``."""
    return np.ascontiguousarray(np.asarray(A, dtype=float).reshape((-1,) + tail))


def _per_matrix3(kernel_name: str, A: np.ndarray, out_tail: tuple[int, ...] = ()) -> np.ndarray:
    """Apply the compiled ``linalg`` kernel ``kernel_name(flat (n, 3, 3), out (n, *out_tail))`` to every
    3 x 3 matrix of ``A`` (..., 3, 3); returns (..., *out_tail)."""
    flat = _flat(A, (3, 3))
    out = np.empty((len(flat),) + out_tail)
    getattr(_linalg(), kernel_name)(flat, out)
    return out.reshape(A.shape[:-2] + out_tail)


def conformal_parts(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(mu, nu)`` complex arrays of shape ``M.shape[:-2]`` (2x2 matrices only)."""
    M = np.asarray(M, dtype=float)
    if _dim(M) != 2:
        raise ValueError(f"conformal parts exist for 2x2 matrices only, got shape {M.shape}")
    mu = 0.5 * (M[..., 0, 0] + M[..., 1, 1]) + 0.5j * (M[..., 1, 0] - M[..., 0, 1])
    nu = 0.5 * (M[..., 0, 0] - M[..., 1, 1]) + 0.5j * (M[..., 0, 1] + M[..., 1, 0])
    return mu, nu


def compose_parts(mu1, nu1, mu2, nu2):
    """Conformal parts of the product ``A B`` from those of ``A`` (1) and ``B`` (2)."""
    return mu1 * mu2 + nu1 * np.conj(nu2), mu1 * nu2 + nu1 * np.conj(mu2)


def inverse_parts(mu, nu, rcond: float = 1e-12):
    """Conformal parts of ``A^-1`` (``(conj(mu), -nu) / det``, ``det = |mu|^2 - |nu|^2``) and a
    singular mask; singular entries are NaN. Compiled (``errplan.kinematics.compiled._inverse_parts_kernel``)
    for arrays of one shape, ``mu`` float or complex and ``nu`` complex: the operations of
    :func:`_inverse_parts_numpy` (the reference), the same bits."""
    mu, nu = np.asarray(mu), np.asarray(nu)
    if not (mu.ndim >= 1 and mu.shape == nu.shape and nu.dtype == np.complex128
            and mu.dtype in (np.float64, np.complex128)):
        return _inverse_parts_numpy(mu, nu, rcond)  # one number: numpy's scalar arithmetic rounds differently
    from .kinematics import compiled

    real_mu = mu.dtype == np.float64
    n = mu.size
    MU = np.zeros((n, 2))
    if real_mu:
        MU[:, 0] = mu.reshape(-1)
    else:
        MU[:] = mu.reshape(-1).view(float).reshape(n, 2)
    NU = compiled.kernel_array(nu.reshape(-1)).view(float).reshape(n, 2)
    IMU, INU = np.empty((n, 2)), np.empty(nu.shape, complex)
    singular = np.empty(mu.shape, bool)
    compiled._inverse_parts_kernel(MU, NU, bool(real_mu), float(rcond), IMU, INU.reshape(-1).view(float).reshape(n, 2),
                                   singular.reshape(-1))
    imu = np.ascontiguousarray(IMU[:, 0]).reshape(mu.shape) if real_mu else IMU.reshape(-1).view(complex).reshape(mu.shape)
    return imu, INU, singular


def _inverse_parts_numpy(mu, nu, rcond: float = 1e-12):
    """:func:`inverse_parts` in numpy: the reference of the compiled path."""
    det = (mu * np.conj(mu)).real - (nu * np.conj(nu)).real
    scale = (mu * np.conj(mu)).real + (nu * np.conj(nu)).real
    singular = ~(np.abs(det) > rcond * scale)
    safe = np.where(singular, np.nan, det)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.conj(mu) / safe, -nu / safe, singular


def inv(A: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``(..., d, d)`` matrices (d = 2, 3) and a mask of the singular ones.

    Singular means ``|det| <= rcond * ||A||_F^d`` (or a non-finite ``det``); those entries are
    returned as NaN, never as inf. ``|det| / ||A||_F^d`` is a scale-free measure of how close
    ``A`` is to singular (at most ``d^(-d/2)``, reached by multiples of orthogonal matrices).
    """
    A = np.asarray(A, dtype=float)
    if _dim(A) == 2:
        return inv2(A, rcond)
    la = _linalg()
    flat = _flat(A, (3, 3))
    out = np.empty_like(flat)
    singular = np.empty(len(flat), bool)
    la._inv3_many(flat, out, float(rcond), singular)
    return out.reshape(A.shape), singular.reshape(A.shape[:-2])


def inv2(A: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of 2x2 matrices and a mask of the singular ones (``|det| <= rcond * ||A||^2``).

    Singular entries are returned as NaN, never as inf. (:func:`inv` for any d.)
    """
    A = np.asarray(A, dtype=float)
    if _dim(A) != 2:
        raise ValueError(f"inv2 takes (..., 2, 2) matrices, got shape {A.shape}; use inv()")
    if A.flags.c_contiguous:
        # compiled (errplan.kinematics.compiled._inv2_kernel): the operations below in the same order, the
        # Frobenius sum as numpy's einsum adds a C-contiguous 2 x 2 block, (a00^2 + a10^2) + (a01^2 + a11^2)
        from .kinematics import compiled

        out = np.empty(A.shape)
        singular = np.empty(A.shape[:-2], bool)
        compiled._inv2_kernel(compiled.kernel_array(A).reshape(-1, 2, 2), float(rcond), out.reshape(-1, 2, 2),
                              singular.reshape(-1))
        return out, singular
    return _inv2_numpy(A, rcond)


def _inv2_numpy(A: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """:func:`inv2` in numpy: the reference of the compiled path (and the path of other memory layouts)."""
    det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    scale = np.einsum("...ij,...ij->...", A, A)
    singular = ~(np.abs(det) > rcond * scale)
    safe = np.where(singular, 1.0, det)
    inv = np.empty_like(A)
    inv[..., 0, 0] = A[..., 1, 1]
    inv[..., 1, 1] = A[..., 0, 0]
    inv[..., 0, 1] = -A[..., 0, 1]
    inv[..., 1, 0] = -A[..., 1, 0]
    inv = inv / safe[..., None, None]
    inv[singular] = np.nan
    return inv, singular


def motion_map(J: np.ndarray, J_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``M = J Jhat^-1`` (actual motion per desired motion at unit gain) and a singular mask
    (``Jhat`` singular in the sense of :func:`inv`; ``M`` is NaN there)."""
    J_hat = np.asarray(J_hat, dtype=float)
    d = _dim(J_hat, "J_hat")
    if np.shape(J)[-2:] != (d, d):
        raise ValueError(f"J must have shape (..., {d}, {d}) like J_hat, got {np.shape(J)}")
    inv_, singular = inv2(J_hat) if d == 2 else inv(J_hat)
    return np.einsum("...ij,...jk->...ik", J, inv_), singular


def G_matrix(M: np.ndarray, k) -> np.ndarray:
    """``G = I - k M`` (P1 eq. 5); ``k`` broadcasts against ``M.shape[:-2]``."""
    M = np.asarray(M, float)
    d = _dim(M)
    return np.eye(d) - np.asarray(k, float)[..., None, None] * M


def g_norm_from_parts(mu: np.ndarray, nu: np.ndarray, k) -> np.ndarray:
    """``||I - k M||_2 = |1 - k mu| + k |nu|`` for ``k >= 0``."""
    k = np.asarray(k, float)
    return np.abs(1.0 - k * mu) + k * np.abs(nu)


def g_norm(M: np.ndarray, k) -> np.ndarray:
    """Largest singular value of ``G = I - k M`` (P1 eq. 6); ``k`` broadcasts against
    ``M.shape[:-2]``."""
    M = np.asarray(M, float)
    if _dim(M) == 2:
        mu, nu = conformal_parts(M)
        return g_norm_from_parts(mu, nu, k)
    k = np.asarray(k, float)
    shape = np.broadcast_shapes(M.shape[:-2], k.shape)
    Mb = _flat(np.broadcast_to(M, shape + (3, 3)), (3, 3))
    kb = np.ascontiguousarray(np.broadcast_to(k, shape), dtype=float).reshape(-1)
    out = np.empty(len(Mb))
    _linalg()._g_norm3_many(Mb, kb, out)
    return out.reshape(shape)


def spectral_norm(A: np.ndarray) -> np.ndarray:
    """Largest singular value: ``|mu| + |nu|`` for 2x2, the compiled closed form for 3x3."""
    A = np.asarray(A, float)
    if _dim(A) == 2:
        mu, nu = conformal_parts(A)
        return np.abs(mu) + np.abs(nu)
    return _per_matrix3("_sigma_max3_many", A)


def phi_hat_max(gn) -> np.ndarray:
    """P1 eq. (10): ``asin(||G||)`` for ``||G|| <= 1``; above 1 the continuous extension
    ``pi - asin(1/||G||)`` (docs/physics.md), a display/cost value, never a certificate."""
    gn = np.asarray(gn, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        above = np.pi - np.arcsin(np.clip(1.0 / np.where(gn > 1.0, gn, 1.0), 0.0, 1.0))
    return np.where(gn <= 1.0, np.arcsin(np.clip(gn, 0.0, 1.0)), above)


def phi_max_from_parts(mu: np.ndarray, nu: np.ndarray) -> np.ndarray:
    """Exact ``|phi_max|`` (rad) from the conformal parts of ``M = J Jhat^-1``."""
    amu, anu = np.abs(mu), np.abs(nu)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(amu > 0, anu / np.where(amu > 0, amu, 1.0), np.inf)
    inside = ratio < 1.0
    val = np.abs(np.angle(mu)) + np.arcsin(np.where(inside, ratio, 0.0))
    return np.where(inside, np.minimum(val, np.pi), np.pi)


def phi_max(M: np.ndarray) -> np.ndarray:
    """Exact largest angle between a desired and the actual motion, over all directions (eq. 9),
    in rad: ``max over unit v of angle(v, M v)``.

    Independent of the gain ``k > 0``. ``pi`` where ``M`` has a real eigenvalue ``<= 0`` (a
    motion reversed or annihilated). 2x2: the conformal closed form; 3x3: the exact 1-D dual
    search of :func:`errplan.linalg.phi_max3` (NaN for a non-finite matrix).
    """
    M = np.asarray(M, float)
    if _dim(M) == 2:
        return phi_max_from_parts(*conformal_parts(M))
    return _per_matrix3("_phi_max3_many", M)


def phi_of_direction(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle from desired motion ``v`` (..., d) to the actual motion ``M v``: signed in the plane
    (counter-clockwise positive), unsigned in [0, pi] in 3-D (there is no orientation)."""
    M = np.asarray(M, float)
    v = np.asarray(v, float)
    d = _dim(M)
    _vec_dim(v, d, "v")
    Mv = np.einsum("...ij,...j->...i", M, v)
    dot = np.einsum("...i,...i->...", v, Mv)
    if d == 3:
        return np.arctan2(np.linalg.norm(np.cross(v, Mv), axis=-1), dot)
    cross = v[..., 0] * Mv[..., 1] - v[..., 1] * Mv[..., 0]
    return np.arctan2(cross, dot)


def p_phi(M: np.ndarray) -> np.ndarray:
    """Unit desired direction (..., d) that attains ``|phi_max|`` (defined up to sign)."""
    M = np.asarray(M, float)
    if _dim(M) == 3:
        return _per_matrix3("_p_phi3_many", M, (3,))
    mu, nu = conformal_parts(M)
    amu, anu = np.abs(mu), np.abs(nu)
    sgn = np.where(np.angle(mu) >= 0, 1.0, -1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.arcsin(np.clip(anu / np.where(amu > 0, amu, 1.0), 0.0, 1.0))
        # Tangent point of the circle mu + nu e^{-2is}: nu e^{-2is} = |nu| e^{i(arg mu + sgn(pi/2 + beta))}
        s = 0.5 * (np.angle(nu) - np.angle(mu) - sgn * (np.pi / 2 + beta))
        # Where the circle reaches the negative real axis the motion can be reversed (phi = pi):
        # use the point x < 0 where the circle meets that axis.
        x = mu.real - np.sqrt(np.maximum(anu**2 - mu.imag**2, 0.0))
        s_rev = 0.5 * (np.angle(nu) - np.angle(x - mu))
    reversed_ = (anu >= amu) | (np.abs(np.angle(mu)) + beta >= np.pi)
    s = np.where(reversed_, s_rev, s)
    return np.stack([np.cos(s), np.sin(s)], axis=-1)


def v_sigma(G: np.ndarray) -> np.ndarray:
    """Right singular vector (..., d) of ``G`` for its largest singular value (up to sign)."""
    G = np.asarray(G, float)
    if _dim(G) == 3:
        return _per_matrix3("_v_sigma3_many", G, (3,))
    mu, nu = conformal_parts(G)
    s = 0.5 * (np.angle(nu) - np.angle(mu))
    return np.stack([np.cos(s), np.sin(s)], axis=-1)


def min_over_gain(Ms: np.ndarray, iters: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Best achievable contraction ``rho* = min over k > 0 of max_i ||I - k M_i||_2`` and its
    gain ``k*`` for each stack ``Ms[..., :, :, :]`` of shape ``(..., m, d, d)``.

    ``max_i ||I - k M_i||`` is convex in ``k``: golden section (``iters`` steps) on
    ``[0, k_max]``, as the planar ``fields.minimize_gain`` (same numbers for d = 2). Where no gain
    contracts, ``rho* = 1`` at ``k* = 0``; in particular wherever some ``M_i`` turns a motion by
    more than 90 deg (``||I - k M|| >= |1 - k v^T M v| > 1``), and wherever some ``M_i`` has a
    non-finite entry: it counts as ``M = 0`` (no motion, ``||I - k 0|| = 1``), as
    ``minimize_gain`` does by replacing non-finite parts by 0. Returns two arrays of shape
    ``Ms.shape[:-3]``.
    """
    Ms = np.asarray(Ms, float)
    d = _dim(Ms)
    if Ms.ndim < 3:
        raise ValueError(f"Ms must have shape (..., m, {d}, {d}), got {Ms.shape}")
    batch, m = Ms.shape[:-3], Ms.shape[-3]
    if d == 3:
        flat = np.ascontiguousarray(Ms.reshape((-1, m, 3, 3)))
        out = np.empty((len(flat), 2))
        _linalg()._min_over_gain3_many(flat, out, int(iters))
        return out[:, 0].reshape(batch), out[:, 1].reshape(batch)
    mu, nu = conformal_parts(Ms.reshape((-1, m, 2, 2)))
    rho, k = min_over_gain_parts(mu, nu, iters)
    return rho.reshape(batch), k.reshape(batch)


def min_over_gain_parts(mu: np.ndarray, nu: np.ndarray, iters: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """The planar :func:`min_over_gain` from the conformal parts ``mu``, ``nu`` (n, m) complex:
    ``max_i ||I - k M_i|| = max_i |1 - k mu_i| + k |nu_i|``, golden section on ``[0, 2 / max |mu|]``.
    Non-finite parts count as ``M = 0``. Returns ``(rho*, k*)``, each (n,)."""
    mu, nu = np.asarray(mu), np.asarray(nu)
    if mu.ndim != 2:  # (n, m, ...) parts of several instances per row
        mu, nu = mu.reshape(mu.shape[0], -1), nu.reshape(nu.shape[0], -1)
    m = mu.shape[1]
    bad = ~np.isfinite(mu) | ~np.isfinite(nu)
    mu = np.where(bad, 0.0, mu)
    nu = np.where(bad, 0.0, nu)
    amax = np.abs(mu).max(axis=1) if m else np.zeros(len(mu))
    kmax = np.where(amax > 0, 2.0 / np.where(amax > 0, amax, 1.0), 1.0)

    def f(k):
        if m == 0:
            return np.ones(len(k))
        return (np.abs(1.0 - k[:, None] * mu) + k[:, None] * np.abs(nu)).max(axis=1)

    a = np.zeros(len(mu))
    b = kmax.copy()
    gr = (math.sqrt(5) - 1) / 2
    c = b - gr * (b - a)
    dd = a + gr * (b - a)
    fc, fd = f(c), f(dd)
    for _ in range(iters):
        left = fc < fd  # the minimum lies in [a, dd]
        a, b = np.where(left, a, c), np.where(left, dd, b)
        new_x = np.where(left, b - gr * (b - a), a + gr * (b - a))
        f_new = f(new_x)
        c, dd, fc, fd = (np.where(left, new_x, dd), np.where(left, c, new_x),
                         np.where(left, f_new, fd), np.where(left, fc, f_new))
    k = 0.5 * (a + b)
    rho = f(k)
    none = rho >= 1.0
    return np.where(none, 1.0, rho), np.where(none, 0.0, k)
