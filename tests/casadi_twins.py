"""casadi twins of errplan's kinematics, the tests' independent reference: Jacobians by automatic
differentiation (it lives with the tests: errplan itself imports casadi in one module only, the gain
schedule).

The numpy models of :mod:`errplan.kinematics.arm` and :mod:`errplan.kinematics.shaft` use closed
forms for speed; the functions here build the same forward models as casadi expressions and let
casadi differentiate them, so every closed-form Jacobian has an independent twin (the tests
compare both with central finite differences). Also here: P2's appendix Jacobian, as printed and
repaired (see :func:`p2_appendix_jacobian`), for the comparison physics.md asks for.

Conventions (docs/physics.md): points ``[y, z]`` (m), ``dir(a) = [sin a, cos a]``, the flexed
shaft of P2 (eqs. 1, 6, 7, 10, 18): the port sits at ``(a, y_m(a))`` in the model frame of the
wrist->tip chord, ``|p - w|^2 = a^2 + y_m(a)^2`` (eq. 18), chord angle
``phi = angle(p - w) - atan(y_m(a) / a)`` (eq. 7), ``tip = w + L dir(phi)`` (eq. 6), and

- ``hold = "tip_force"``: the load is ``Ft/EI`` (= ``t`` of shaft.py), ``y_m = -t a b^2 / 3``;
- ``hold = "port_force"``: the load is ``Fp/EI``, ``y_m = -(Fp/EI) a^2 b^2 / (3L)`` (eq. 10);
- ``hold = "port_deflection"``: the load is ``y_m(a)`` itself (m).

The load is what stays constant when the Jacobian ``d tip / d w`` is taken (the port is fixed
too). The implicit equation (18) for ``a`` is solved inside casadi by a Newton rootfinder, so the
derivative is the exact implicit one.
"""
from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np

HOLDS = ("tip_force", "port_force", "port_deflection")


def _dir(a):
    return ca.vertcat(ca.sin(a), ca.cos(a))


# ----------------------------------------------------------------------------- arm
@lru_cache(maxsize=32)
def arm_functions(base: tuple[float, float], l1: float, l2: float, home: tuple[float, float]) -> tuple[ca.Function, ca.Function]:
    """``(fk, jac)``: casadi Functions ``q (2) -> w (2)`` and ``q -> dw/dq (2x2)`` of the planar arm."""
    q = ca.SX.sym("q", 2)
    a1 = q[0] + home[0]
    a2 = a1 + q[1] + home[1]
    w = ca.DM(list(base)) + l1 * _dir(a1) + l2 * _dir(a2)
    fk = ca.Function("arm_fk", [q], [w], ["q"], ["w"])
    jac = ca.Function("arm_jac", [q], [ca.jacobian(w, q)], ["q"], ["J"])
    return fk, jac


def _arm_key(arm) -> tuple:
    return (tuple(float(v) for v in arm.base), float(arm.l1), float(arm.l2), tuple(float(v) for v in arm.home))


def arm_forward(arm, q: np.ndarray) -> np.ndarray:
    """Wrist positions (..., 2) of :class:`errplan.kinematics.arm.Arm` ``arm`` by casadi."""
    fk, _ = arm_functions(*_arm_key(arm))
    return _batched(fk, [np.asarray(q, float)], (2,))


def arm_jacobian(arm, q: np.ndarray) -> np.ndarray:
    """``dw/dq`` (..., 2, 2) by casadi AD."""
    _, jac = arm_functions(*_arm_key(arm))
    return _batched(jac, [np.asarray(q, float)], (2, 2))


# ----------------------------------------------------------------------------- shaft
@lru_cache(maxsize=32)
def lever_functions(L: float) -> tuple[ca.Function, ca.Function]:
    """``(tip, jac)``: the rigid lever (P2 eq. 17), ``(w, p) -> tip`` and ``(w, p) -> d tip/d w``."""
    w = ca.SX.sym("w", 2)
    p = ca.SX.sym("p", 2)
    d = p - w
    tip = w + L * d / ca.norm_2(d)
    return (ca.Function("lever_tip", [w, p], [tip], ["w", "p"], ["tip"]),
            ca.Function("lever_jac", [w, p], [ca.jacobian(tip, w)], ["w", "p"], ["J"]))


def _deflection(a, L: float, load, hold: str):
    b = L - a
    if hold == "tip_force":
        return -load * a * b * b / 3.0
    if hold == "port_force":
        return -load * a * a * b * b / (3.0 * L)
    raise ValueError(f"hold = {hold!r}: expected one of {', '.join(HOLDS)}")


@lru_cache(maxsize=32)
def _port_position_solver(L: float, hold: str) -> ca.Function:
    """Newton rootfinder of eq. (18) for ``a`` given ``[rho, load]``, started at ``a = rho``."""
    a = ca.MX.sym("a")
    par = ca.MX.sym("par", 2)
    ym = _deflection(a, L, par[1], hold)
    g = a * a + ym * ym - par[0] * par[0]
    return ca.rootfinder("p2_eq18", "newton", {"x": a, "p": par, "g": g}, {"abstol": 1e-15, "max_iter": 50})


@lru_cache(maxsize=32)
def flexed_functions(L: float, hold: str = "tip_force") -> tuple[ca.Function, ca.Function, ca.Function]:
    """``(tip, jac, shape)`` of P2's flexed shaft with ``load`` held constant (see module doc).

    ``tip(w, p, load)`` (2), ``jac(w, p, load)`` = d tip/d w (2x2) by casadi AD through the
    rootfinder, ``shape(w, p, load)`` = ``[a, y_m(a), phi]``.
    """
    if hold not in HOLDS:
        raise ValueError(f"hold = {hold!r}: expected one of {', '.join(HOLDS)}")
    w = ca.MX.sym("w", 2)
    p = ca.MX.sym("p", 2)
    load = ca.MX.sym("load")
    d = p - w
    rho = ca.norm_2(d)
    theta = ca.atan2(d[0], d[1])
    if hold == "port_deflection":
        ym = load
        a = ca.sqrt(rho * rho - ym * ym)
    else:
        a = _port_position_solver(L, hold)(rho, ca.vertcat(rho, load))
        ym = _deflection(a, L, load, hold)
    phi = theta - ca.atan(ym / a)
    tip = w + L * _dir(phi)
    args, names = [w, p, load], ["w", "p", "load"]
    return (ca.Function("flexed_tip", args, [tip], names, ["tip"]),
            ca.Function("flexed_jac", args, [ca.jacobian(tip, w)], names, ["J"]),
            ca.Function("flexed_shape", args, [ca.vertcat(a, ym, phi)], names, ["shape"]))


@lru_cache(maxsize=32)
def flexed_functions_3d(L: float) -> tuple[ca.Function, ca.Function]:
    """``(tip, jac)`` of the 3-D flexed shaft (docs/physics.md "Flexed shaft in 3-D"), built
    independently of shaft.py: the world load ``t`` (3) over EI, its part normal to the wrist->port
    line ``t_perp = t - (t.u) u`` bends the shaft in the plane of ``u`` and ``t_perp`` as P2's planar
    beam with load ``|t_perp|`` (eq. 18 by casadi's rootfinder). ``jac`` = d tip / d w holding the
    port and the world vector ``t``, by AD."""
    w = ca.MX.sym("w", 3)
    p = ca.MX.sym("p", 3)
    t = ca.MX.sym("t", 3)
    d = p - w
    rho = ca.norm_2(d)
    u = d / rho
    tp = t - ca.dot(t, u) * u
    tau = ca.norm_2(tp)
    n = tp / tau
    a = _port_position_solver(L, "tip_force")(rho, ca.vertcat(rho, tau))
    ym = _deflection(a, L, tau, "tip_force")
    beta = -ca.atan(ym / a)
    tip = w + L * (ca.cos(beta) * u + ca.sin(beta) * n)
    args, names = [w, p, t], ["w", "p", "t"]
    return (ca.Function("flexed_tip3", args, [tip], names, ["tip"]),
            ca.Function("flexed_jac3", args, [ca.jacobian(tip, w)], names, ["J"]))


def flexed_tip_3d(w, p, L: float, t) -> np.ndarray:
    return _batched(flexed_functions_3d(float(L))[0], [w, p, t], (3,))


def flexed_jacobian_3d(w, p, L: float, t) -> np.ndarray:
    """``d tip / d w`` (..., 3, 3) of the 3-D flexed shaft by casadi AD, port and world load held."""
    return _batched(flexed_functions_3d(float(L))[1], [w, p, t], (3, 3))


def _batched(f: ca.Function, args: list[np.ndarray], out_shape: tuple[int, ...]) -> np.ndarray:
    """Evaluate a casadi Function over leading batch axes of numpy arguments (last axis = input)."""
    arrs = [np.asarray(x, float) for x in args]
    lead = np.broadcast_shapes(*[x.shape[:-1] if x.ndim and f.size1_in(i) > 1 else x.shape
                                 for i, x in enumerate(arrs)])
    cols = []
    for i, x in enumerate(arrs):
        k = f.size1_in(i)
        if k > 1:
            x = np.broadcast_to(x, lead + (k,)).reshape(-1, k).T
        else:
            x = np.broadcast_to(x, lead).reshape(1, -1)
        cols.append(x)
    n = int(np.prod(lead)) if lead else 1
    out = np.asarray(f.map(n)(*cols)) if n > 1 else np.asarray(f(*cols))
    # casadi stacks mapped outputs horizontally: (rows, cols * n), column-major within a matrix
    r = int(np.prod(out_shape[:1]))
    c = int(np.prod(out_shape[1:])) if len(out_shape) > 1 else 1
    out = out.reshape(r, n, c).transpose(1, 0, 2) if c > 1 else out.reshape(r, n).T
    return out.reshape(lead + out_shape)


def lever_tip(w, p, L: float) -> np.ndarray:
    return _batched(lever_functions(float(L))[0], [w, p], (2,))


def lever_jacobian(w, p, L: float) -> np.ndarray:
    """``d tip / d w`` (..., 2, 2) of the rigid lever by casadi AD."""
    return _batched(lever_functions(float(L))[1], [w, p], (2, 2))


def flexed_tip(w, p, L: float, load, hold: str = "tip_force") -> np.ndarray:
    return _batched(flexed_functions(float(L), hold)[0], [w, p, load], (2,))


def flexed_jacobian(w, p, L: float, load, hold: str = "tip_force") -> np.ndarray:
    """``d tip / d w`` (..., 2, 2) of the flexed shaft by casadi AD, ``load`` held (module doc)."""
    return _batched(flexed_functions(float(L), hold)[1], [w, p, load], (2, 2))


def flexed_shape(w, p, L: float, load, hold: str = "tip_force") -> np.ndarray:
    """``[a, y_m(a), phi]`` (..., 3) of the flexed shaft."""
    return _batched(flexed_functions(float(L), hold)[2], [w, p, load], (3,))


# ----------------------------------------------------------------------------- P2's appendix
def p2_appendix_jacobian(w, p, L: float, a, ym, *, repaired: bool = False, angle: str = "port") -> np.ndarray:
    """P2's appendix flexion Jacobian in errplan's ``[y, z]`` order (..., 2, 2).

    As printed (P2's ``x`` is errplan's ``z``, its ``y`` is ``y``)::

        J11 = 1 + L sin(gamma - phi) (dY/Lm^2 + dX (temp2 - temp1) / temp3)
        J12 =     L sin(gamma - phi) (-dX/Lm^2 + dY (temp2 - temp1) / temp3)
        J21 =   - L cos(gamma - phi) (-dY/Lm^2 + dX (temp1 - temp2) / temp3)
        J22 = 1 - L cos(gamma - phi) (dX/Lm^2 + dY (temp1 - temp2) / temp3)
        gamma = atan(y_m(a)/a), temp1 = 3 L y_m(a), temp2 = (2a - L) temp1,
        temp3 = (3 L a + temp2 y_m(a)) (a^2 + y_m(a)^2), dX = x_p - x_w, dY = y_p - y_w, Lm = |p - w|

    ``angle``: what the printed ``phi`` stands for, ``"port"`` (the angle of p - w, which makes
    ``gamma - phi`` minus the chord angle of eq. 7) or ``"chord"`` (eq. 7's phi itself).

    ``repaired=True`` replaces the two garbled terms by what the chain rule with ``Fp/EI`` held
    constant gives (``dy_m/da = 2 y_m (2a - L) / (a (a - L))``): ``temp2 = 3 L a dy_m/da =
    2 (2a - L) temp1 / (a - L)`` and ``temp3 = (3 L a + temp2 y_m / a)(a^2 + y_m^2)``.
    """
    w, p = np.asarray(w, float), np.asarray(p, float)
    a, ym = np.asarray(a, float), np.asarray(ym, float)
    dX = p[..., 1] - w[..., 1]  # P2's x is errplan's z
    dY = p[..., 0] - w[..., 0]
    lm2 = dX * dX + dY * dY
    gamma = np.arctan(ym / a)
    port_angle = np.arctan2(dY, dX)
    if angle == "port":
        phi = port_angle
    elif angle == "chord":
        phi = port_angle - gamma
    else:
        raise ValueError(f"angle = {angle!r}: expected 'port' or 'chord'")
    temp1 = 3.0 * L * ym
    if repaired:
        temp2 = 2.0 * (2.0 * a - L) * temp1 / (a - L)
        temp3 = (3.0 * L * a + temp2 * ym / a) * (a * a + ym * ym)
    else:
        temp2 = (2.0 * a - L) * temp1
        temp3 = (3.0 * L * a + temp2 * ym) * (a * a + ym * ym)
    s, c = np.sin(gamma - phi), np.cos(gamma - phi)
    j11 = 1 + L * s * (dY / lm2 + dX * (temp2 - temp1) / temp3)
    j12 = L * s * (-dX / lm2 + dY * (temp2 - temp1) / temp3)
    j21 = -L * c * (-dY / lm2 + dX * (temp1 - temp2) / temp3)
    j22 = 1 - L * c * (dX / lm2 + dY * (temp1 - temp2) / temp3)
    # P2 order (x, y) = (z, y): [[dz_t/dz_w, dz_t/dy_w], [dy_t/dz_w, dy_t/dy_w]] -> errplan [y, z]
    return np.stack([np.stack([j22, j21], -1), np.stack([j12, j11], -1)], -2)
