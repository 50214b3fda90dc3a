"""Kinematic-error metrics of P1 Sec. II-B, in closed form for the plane.

Every 2x2 real matrix acts on ``v = [v0, v1]`` like ``z -> mu z + nu conj(z)`` on the complex
number ``z = v0 + i v1``, with the *conformal* part ``mu = (M00 + M11)/2 + i (M10 - M01)/2`` and
the *anticonformal* part ``nu = (M00 - M11)/2 + i (M01 + M10)/2``. Then

- the singular values are ``|mu| + |nu|`` and ``||mu| - |nu||``, so for the motion map
  ``M = J Jhat^-1`` and ``G = I - k M``: ``||G|| = |1 - k mu| + k |nu|`` (P1 eq. 6);
- the actual motion for a desired unit motion ``e^{is}`` is ``e^{is} (mu + nu e^{-2is})``: its
  angle to the desired motion runs over ``arg`` of a circle of centre ``mu`` and radius ``|nu|``,
  so ``|phi_max| = min(pi, |arg mu| + asin(|nu|/|mu|))`` when ``|nu| < |mu|`` and ``pi``
  otherwise (P1 eq. 9, which the paper only searched numerically).

Matrices have shape ``(..., 2, 2)`` and vectors ``(..., 2)``; leading axes are batch axes.
"""
from __future__ import annotations

import numpy as np


def conformal_parts(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(mu, nu)`` complex arrays of shape ``M.shape[:-2]``."""
    M = np.asarray(M, dtype=float)
    mu = 0.5 * (M[..., 0, 0] + M[..., 1, 1]) + 0.5j * (M[..., 1, 0] - M[..., 0, 1])
    nu = 0.5 * (M[..., 0, 0] - M[..., 1, 1]) + 0.5j * (M[..., 0, 1] + M[..., 1, 0])
    return mu, nu


def compose_parts(mu1, nu1, mu2, nu2):
    """Conformal parts of the product ``A B`` from those of ``A`` (1) and ``B`` (2)."""
    return mu1 * mu2 + nu1 * np.conj(nu2), mu1 * nu2 + nu1 * np.conj(mu2)


def inverse_parts(mu, nu, rcond: float = 1e-12):
    """Conformal parts of ``A^-1`` (``(conj(mu), -nu) / det``, ``det = |mu|^2 - |nu|^2``) and a
    singular mask; singular entries are NaN."""
    det = (mu * np.conj(mu)).real - (nu * np.conj(nu)).real
    scale = (mu * np.conj(mu)).real + (nu * np.conj(nu)).real
    singular = ~(np.abs(det) > rcond * scale)
    safe = np.where(singular, np.nan, det)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.conj(mu) / safe, -nu / safe, singular


def inv2(A: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of 2x2 matrices and a mask of the singular ones (``|det| <= rcond * ||A||^2``).

    Singular entries are returned as NaN, never as inf.
    """
    A = np.asarray(A, dtype=float)
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
    """``M = J Jhat^-1`` (actual motion per desired motion at unit gain) and a singular mask."""
    inv, singular = inv2(J_hat)
    return np.einsum("...ij,...jk->...ik", J, inv), singular


def G_matrix(M: np.ndarray, k) -> np.ndarray:
    """``G = I - k M`` (P1 eq. 5)."""
    M = np.asarray(M, float)
    return np.eye(2) - np.asarray(k, float)[..., None, None] * M


def g_norm_from_parts(mu: np.ndarray, nu: np.ndarray, k) -> np.ndarray:
    """``||I - k M||_2 = |1 - k mu| + k |nu|`` for ``k >= 0``."""
    k = np.asarray(k, float)
    return np.abs(1.0 - k * mu) + k * np.abs(nu)


def g_norm(M: np.ndarray, k) -> np.ndarray:
    """Largest singular value of ``G = I - k M`` (P1 eq. 6)."""
    mu, nu = conformal_parts(M)
    return g_norm_from_parts(mu, nu, k)


def spectral_norm(A: np.ndarray) -> np.ndarray:
    """Largest singular value of 2x2 matrices: ``|mu| + |nu|``."""
    mu, nu = conformal_parts(A)
    return np.abs(mu) + np.abs(nu)


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
    """Exact largest angle between a desired and the actual motion, over all directions (eq. 9).

    Independent of the gain ``k > 0``.
    """
    return phi_max_from_parts(*conformal_parts(M))


def phi_of_direction(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Signed angle from desired motion ``v`` (..., 2) to the actual motion ``M v``."""
    Mv = np.einsum("...ij,...j->...i", np.asarray(M, float), np.asarray(v, float))
    v = np.asarray(v, float)
    cross = v[..., 0] * Mv[..., 1] - v[..., 1] * Mv[..., 0]
    dot = np.einsum("...i,...i->...", v, Mv)
    return np.arctan2(cross, dot)


def p_phi(M: np.ndarray) -> np.ndarray:
    """Unit desired direction (..., 2) that attains ``|phi_max|`` (defined up to sign)."""
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
    """Right singular vector (..., 2) of ``G`` for its largest singular value (up to sign)."""
    mu, nu = conformal_parts(G)
    s = 0.5 * (np.angle(nu) - np.angle(mu))
    return np.stack([np.cos(s), np.sin(s)], axis=-1)
