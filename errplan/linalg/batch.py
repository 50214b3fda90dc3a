"""Loops of the kernels over stacked matrices, for :mod:`errplan.metrics`' vectorised functions."""
from __future__ import annotations


from .basics import NAN, _jit, inv3, singular3
from .singular import g_norm3, sigma_max3, v_sigma3
from .phimax import p_phi3, phi_max3
from .gain import min_over_gain3


# ============================================================================ batch loops
# Flat loops used by errplan.metrics (one call per array; the scalar kernels above are the API for
# compiled callers).
@_jit
def _inv3_many(A, out, rcond, singular):
    for i in range(A.shape[0]):
        det = inv3(A[i], out[i])
        s = singular3(A[i], det, rcond)
        singular[i] = s
        if s:
            for a in range(3):
                for b in range(3):
                    out[i, a, b] = NAN


@_jit
def _g_norm3_many(M, k, out):
    for i in range(M.shape[0]):
        out[i] = g_norm3(M[i], k[i])


@_jit
def _sigma_max3_many(A, out):
    for i in range(A.shape[0]):
        out[i] = sigma_max3(A[i])


@_jit
def _phi_max3_many(M, out):
    for i in range(M.shape[0]):
        out[i] = phi_max3(M[i])


@_jit
def _p_phi3_many(M, out):
    for i in range(M.shape[0]):
        p_phi3(M[i], out[i])


@_jit
def _v_sigma3_many(G, out):
    for i in range(G.shape[0]):
        v_sigma3(G[i], out[i])


@_jit
def _min_over_gain3_many(Ms, out, iters):
    for i in range(Ms.shape[0]):
        min_over_gain3(Ms[i], Ms.shape[1], out[i], iters)
