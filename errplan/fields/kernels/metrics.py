"""Metrics of a motion map ``M``: ``||I - k M||_2`` (:func:`gnorm`, :func:`gval` from the lever's reduced
form), the exact ``|phi_max|`` (:func:`phimax`) and its cheap bound (:func:`phi_bound`)."""
from __future__ import annotations

import math

from ...jit import njit
from ...linalg import _smax3, phi_max3
from .instance import _gnorm2, _gval_block


# ----------------------------------------------------------------------------- metrics of M
@njit(cache=True, error_model="numpy", literal_args="d")
def gnorm(d, Mb, j, k):
    """``||I - k M||_2`` of ``M = Mb[j]``: ``|1 - k mu| + k |nu|`` in the plane, the closed-form
    sigma_max in 3-D. ``d`` (2 or 3) is a compile-time constant in the search: one branch is compiled."""
    if d == 2:
        return _gnorm2(Mb[j, 0, 0], Mb[j, 0, 1], Mb[j, 1, 0], Mb[j, 1, 1], k)
    return _smax3(1.0 - k * Mb[j, 0, 0], -k * Mb[j, 0, 1], -k * Mb[j, 0, 2],
                  -k * Mb[j, 1, 0], 1.0 - k * Mb[j, 1, 1], -k * Mb[j, 1, 2],
                  -k * Mb[j, 2, 0], -k * Mb[j, 2, 1], 1.0 - k * Mb[j, 2, 2])


@njit(cache=True, error_model="numpy", literal_args="d")
def gval(d, Mb, Pb, j, k):
    """``||I - k M||_2`` of instance ``j`` as :func:`gnorm`, from the reduced form in ``Pb[j]`` where
    :func:`_instance3` left one (the 3-D lever): ``max(|1 - k Pb[j, 4]|, sigma_max(I - k B))`` with
    ``B = [[Pb[j, 0], Pb[j, 1]], [Pb[j, 2], Pb[j, 3]]]``, the 2 x 2 value by its conformal parts
    (``|mu| + |nu|``): no eigenvalue cubic, no trigonometry."""
    if d == 2:
        return gnorm(2, Mb, j, k)
    b00 = Pb[j, 0]
    if not b00 == b00:
        return gnorm(3, Mb, j, k)
    return _gval_block(b00, Pb[j, 1], Pb[j, 2], Pb[j, 3], Pb[j, 4], k)


@njit(cache=True, error_model="numpy")
def phimax(Mb, j):
    """Exact ``|phi_max|`` of ``M = Mb[j]`` (d x d, either d); the search calls :func:`_phimax`."""
    if Mb.shape[1] == 2:
        return _phimax(2, Mb, j)
    return _phimax(3, Mb, j)


@njit(cache=True, error_model="numpy", literal_args="d")
def _phimax(d, Mb, j):
    """Exact ``|phi_max|`` of ``M = Mb[j]``: the conformal closed form in the plane, the S^2 method
    of errplan.linalg in 3-D (``d`` as :func:`gnorm`'s)."""
    if d == 2:
        mr = 0.5 * (Mb[j, 0, 0] + Mb[j, 1, 1])
        mi = 0.5 * (Mb[j, 1, 0] - Mb[j, 0, 1])
        amu = math.sqrt(mr * mr + mi * mi)
        anu = math.sqrt((0.5 * (Mb[j, 0, 0] - Mb[j, 1, 1])) ** 2 + (0.5 * (Mb[j, 0, 1] + Mb[j, 1, 0])) ** 2)
        if not amu > 0.0:
            return math.pi
        ratio = anu / amu
        if not ratio < 1.0:
            return math.pi
        return min(math.pi, abs(math.atan2(mi, mr)) + math.asin(ratio))
    return phi_max3(Mb[j])


@njit(cache=True, error_model="numpy")
def phi_bound(Mb, j):
    """A cheap upper bound of ``|phi_max|`` of ``M = Mb[j]`` (3-D): for any k > 0 the actual motion
    k M v lies in the ball of radius ||I - k M|| |v| around v, so the angle is at most
    asin(||I - k M||) when that is below 1 (P1 eq. 10). k = tr(M) / ||M||_F^2 (the Frobenius-best
    gain); pi when no bound below pi follows."""
    tr = Mb[j, 0, 0] + Mb[j, 1, 1] + Mb[j, 2, 2]
    f = 0.0
    for a in range(3):
        for b in range(3):
            f += Mb[j, a, b] * Mb[j, a, b]
    if not (tr > 0.0 and f > 0.0):
        return math.pi
    g = gnorm(3, Mb, j, tr / f)
    return math.asin(g) if g < 1.0 else math.pi
