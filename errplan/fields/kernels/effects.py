"""The exact effects path in 3-D, compiled: ``M = R J Jhat^-1`` per (tip, instance) of a truth whose
links follow the encoders in closed form (``joint_geometry``, ``joint_offset``, ``instrument_length``,
``tracker_registration``, ``port_offset``; no gravity sag, no world load, no truth's own shaft load) under
the rigid controller. The arithmetic of :meth:`errplan.fields.evaluator.SpatialEffectsEvaluator.parts`
(its reference, equal to about 1e-12) in one loop: the true shaft's wrist under the instance's load, the
true arm's inverse of it (the declared arm's exact inverse, refined on the true chain by its projected
Gauss-Newton: the same branch), the true ``J`` (the true shaft's Jacobian at the true wrist times the
true arm's), the controller's ``Jhat`` (the lever through the estimate on the declared arm at the same
encoder angles times the declared arm's Jacobian)."""
from __future__ import annotations

import math

import numpy as np

from ...jit import njit
from ...kinematics.urdf.chain import _rows_ok, _solve, fk_point, ik_point, jac_point
from ...linalg import inv3
from .instance import _flexed_J3, _lever_J, _perp_basis, _solve_b


@njit(cache=True, error_model="numpy")
def _effects_maps3(X, TH, base_port, est, L, Lt, decl, rmap, true_chain, refine, offset, R, M, ok):
    """Rows ``k``: tip ``X[k]`` (3,), instance ``TH[k]`` (dx, dy, dz, tau, psi) with ``base_port`` the true
    port before the instance's offset; ``L`` the declared instrument, ``Lt`` the true one; ``decl`` the
    declared chain and its reachability map ``rmap``, ``true_chain`` the true one (``refine``: it differs
    from the declared); ``offset`` the joint offsets (link = encoder + offset); ``R`` the tracker's
    rotation. Into ``M[k]`` (3, 3) ``R J Jhat^-1`` (NaN where not ``ok[k]``) and ``ok[k]``."""
    S = np.zeros((8, 3, 3))
    V = np.zeros((9, 3))
    q = np.empty(3)
    qe = np.empty(3)
    wf = np.empty(3)
    Ja = np.empty((3, 3))
    Jw = np.empty((3, 3))
    Jt = np.empty((3, 3))
    Jh = np.empty((3, 3))
    Jinv = np.empty((3, 3))
    RJ = np.empty((3, 3))
    for k in range(X.shape[0]):
        ok[k] = False
        for i in range(3):
            for j in range(3):
                M[k, i, j] = math.nan
        p0, p1, p2 = base_port[0] + TH[k, 0], base_port[1] + TH[k, 1], base_port[2] + TH[k, 2]
        e0, e1, e2 = X[k, 0] - p0, X[k, 1] - p1, X[k, 2] - p2
        r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if not (r > 1e-9 and r < Lt):
            continue
        tau = TH[k, 3]
        p = V[0]
        w = V[2]
        tvec = V[3]
        e1v = V[4]
        f1 = V[5]
        f2 = V[6]
        p[0], p[1], p[2] = p0, p1, p2
        a = 0.0
        if tau == 0.0:
            w[0], w[1], w[2] = X[k, 0] - Lt * e0 / r, X[k, 1] - Lt * e1 / r, X[k, 2] - Lt * e2 / r
            tvec[0] = tvec[1] = tvec[2] = 0.0
        else:  # the bending plane holds e and the direction psi about it (as _instance3)
            e1v[0], e1v[1], e1v[2] = e0 / r, e1 / r, e2 / r
            _perp_basis(e1v, f1, f2)
            cp, sp = math.cos(TH[k, 4]), math.sin(TH[k, 4])
            b = _solve_b(r, Lt, tau)
            al = math.atan(tau * (Lt - b) * b / 3.0)
            ca, sa = math.cos(al), math.sin(al)
            a = Lt - b
            for i in range(3):
                w[i] = X[k, i] - Lt * (ca * e1v[i] - sa * (cp * f1[i] + sp * f2[i]))
            rho = math.sqrt((p[0] - w[0]) ** 2 + (p[1] - w[1]) ** 2 + (p[2] - w[2]) ** 2)
            cu = 0.0
            for i in range(3):
                cu += (ca * e1v[i] - sa * (cp * f1[i] + sp * f2[i])) * (p[i] - w[i]) / rho
            nn = 0.0
            for i in range(3):
                ci = ca * e1v[i] - sa * (cp * f1[i] + sp * f2[i])
                tvec[i] = ci - cu * (p[i] - w[i]) / rho
                nn += tvec[i] * tvec[i]
            nn = math.sqrt(nn)
            for i in range(3):
                tvec[i] = tau * tvec[i] / nn
        if not (math.isfinite(w[0]) and math.isfinite(w[1]) and math.isfinite(w[2])):
            continue
        # the true arm's inverse of the true wrist: the declared arm's, refined on the true chain
        if not ik_point(decl, rmap, w[0], w[1], w[2], q):
            continue
        if refine:
            good, a0, a1, a2 = _solve(true_chain, w[0], w[1], w[2], q[0], q[1], q[2], 60)
            if not good:
                continue
            q[0], q[1], q[2] = a0, a1, a2
            fk_point(true_chain, q, wf)
            if not (abs(wf[0] - w[0]) < 1e-9 and abs(wf[1] - w[1]) < 1e-9 and abs(wf[2] - w[2]) < 1e-9
                    and _rows_ok(decl, q[0], q[1], q[2], 1e-12)):
                continue
        for i in range(3):
            qe[i] = q[i] - offset[i]
        # the true J: the true shaft's at the true arm's wrist times the true arm's Jacobian
        fk_point(true_chain, q, wf)
        jac_point(true_chain, q, Ja)
        for i in range(3):
            w[i] = wf[i]
        if tau == 0.0:
            _lever_J(w, p, Lt, Jw)
        else:
            rho = math.sqrt((p[0] - w[0]) ** 2 + (p[1] - w[1]) ** 2 + (p[2] - w[2]) ** 2)
            ut = 0.0
            for i in range(3):
                ut += tvec[i] * (p[i] - w[i]) / rho
            tp = 0.0
            for i in range(3):
                tp += (tvec[i] - ut * (p[i] - w[i]) / rho) ** 2
            a = _solve_a(rho, Lt, math.sqrt(tp))
            _flexed_J3(V, 2, 0, 3, Lt, a, Jw, S)
        for i in range(3):
            for j in range(3):
                Jt[i, j] = Jw[i, 0] * Ja[0, j] + Jw[i, 1] * Ja[1, j] + Jw[i, 2] * Ja[2, j]
        for i in range(3):
            for j in range(3):
                RJ[i, j] = R[i, 0] * Jt[0, j] + R[i, 1] * Jt[1, j] + R[i, 2] * Jt[2, j]
        # the controller's Jhat: the lever through the estimate on the declared arm, same encoder angles
        fk_point(decl, qe, wf)
        jac_point(decl, qe, Ja)
        _lever_J(wf, est, L, Jw)
        for i in range(3):
            for j in range(3):
                Jh[i, j] = Jw[i, 0] * Ja[0, j] + Jw[i, 1] * Ja[1, j] + Jw[i, 2] * Ja[2, j]
        det = inv3(Jh, Jinv)
        fro = 0.0
        for i in range(3):
            for j in range(3):
                fro += Jh[i, j] * Jh[i, j]
        fro = math.sqrt(fro)
        if not abs(det) > 1e-12 * fro * fro * fro:
            continue
        for i in range(3):
            for j in range(3):
                M[k, i, j] = RJ[i, 0] * Jinv[0, j] + RJ[i, 1] * Jinv[1, j] + RJ[i, 2] * Jinv[2, j]
        ok[k] = True


@njit(cache=True, error_model="numpy")
def _solve_a(rho, L, t):
    """The port's position ``a`` along the chord of a flexed shaft whose wrist is ``rho`` from the port
    under the normal load ``t``: ``rho^2 = a^2 (1 + (t (L - a)^2 / 3)^2)`` by Newton's method from
    ``a = rho`` (kinematics.shaft._solve_a)."""
    a = rho
    for _ in range(8):
        s = t * (L - a) ** 2 / 3.0
        ds = -2.0 * t * (L - a) / 3.0
        h = 1.0 + s * s
        f = a * a * h - rho * rho
        a = a - f / (2.0 * a * h + a * a * 2.0 * s * ds)
    return a
