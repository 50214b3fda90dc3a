"""The instrument shaft: P2's rigid lever (eq. 17) and simply supported flexed beam (eqs. 1-18).

Points are ``[y, z]`` (m) with shape ``(..., 2)`` in the plane and ``[x, y, z]`` with shape
``(..., 3)`` in space (the lever functions and :func:`flexed_tip`/:func:`flexed_jacobian` take
either). In space the load ``t`` is a world-frame vector (..., 3) of tip load over EI: its
component normal to the wrist->port line bends the shaft in the plane of that line and the
component, exactly as the planar beam with load ``|t_perp|`` (docs/physics.md "Flexed shaft in
3-D"); the Jacobian holds the port and the world vector ``t`` constant (to first order the same
as holding the lateral load constant, the planar convention). In the plane: ``L`` is the shaft length (wrist pivot to tip);
``t`` is the lateral tip load over flexural rigidity, ``Ft/EI`` (1/m^2), positive along the
normal ``dir'(phi)`` of the wrist->tip chord (the side of increasing angle). Only ``t`` matters
(docs/physics.md); ``t = 0`` is the rigid lever.

Model frame (P2 Fig. 2/4): wrist at ``x_m = 0``, tip at ``x_m = L`` on the chord, port at
``(a, y_m(a))`` with ``y_m(a) = -(Fp/EI) a^2 b^2 / (3L) = -t a b^2 / 3`` (eq. 10 with the moment
balance ``Fp = Ft L / a``), ``b = L - a``. The chord angle is ``phi = angle(p - w) - atan(y_m(a)/a)``
(eq. 7) and ``|p - w|^2 = a^2 + y_m(a)^2`` (eq. 18).

The flexed-shaft Jacobian ``d tip / d w`` holds the port and ``t`` constant; it is derived in
closed form by implicit differentiation and checked against casadi AD in the tests.
"""
from __future__ import annotations

import math

import numpy as np

from .arm import _compiled, angle_of, direction, direction_derivative
from .newton import NEWTON_ITERS as _NEWTON_ITERS


def _norm(v: np.ndarray) -> np.ndarray:
    if v.shape[-1] == 2:
        return np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2)
    return np.sqrt(np.sum(v * v, axis=-1))


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., :, None] * b[..., None, :]


# ----------------------------------------------------------------------------- rigid lever
def lever_tip(w: np.ndarray, p: np.ndarray, L: float) -> np.ndarray:
    """Tip of a straight shaft from wrist ``w`` through port ``p`` (P2 eq. 17)."""
    w, p = np.asarray(w, float), np.asarray(p, float)
    d = p - w
    return w + L * d / _norm(d)[..., None]


def lever_jacobian(w: np.ndarray, p: np.ndarray, L: float) -> np.ndarray:
    """``d tip / d w`` of the rigid lever (..., 2, 2) = ``u u^T + (1 - L/rho) n n^T``.

    ``u`` is the unit wrist->port direction, ``n`` its normal and ``rho = |p - w|``. Singular
    where the tip reaches the port (``rho = L``); unbounded as the wrist approaches the port.
    """
    w, p = np.asarray(w, float), np.asarray(p, float)
    d = p - w
    rho = _norm(d)
    u = d / rho[..., None]
    if d.shape[-1] == 3:  # I - (L/rho)(I - u u^T) (docs/physics.md "Lever in 3-D")
        return np.eye(3) - (L / rho)[..., None, None] * (np.eye(3) - _outer(u, u))
    n = np.stack([u[..., 1], -u[..., 0]], axis=-1)
    return _outer(u, u) + (1.0 - L / rho)[..., None, None] * _outer(n, n)


def lever_parts(w: np.ndarray, p: np.ndarray, L: float) -> tuple[np.ndarray, np.ndarray]:
    """Conformal parts ``(mu, nu)`` of :func:`lever_jacobian` (see :mod:`errplan.metrics`).

    ``J = I - (L/rho) n n^T``: ``mu = 1 - L/(2 rho)``, ``nu = -(L/(2 rho)) n_c^2`` with the normal
    as a complex number ``n_c = (dz - i dy)/rho``. No trigonometry: the fields' fast path. Compiled
    (:func:`.compiled._lever_parts_kernel`) where the ports are one or one per wrist: the operations of
    :func:`_lever_parts_numpy` (the reference), the same bits.
    """
    w, p = np.asarray(w, float), np.asarray(p, float)
    if w.ndim < 2 or w.shape[-1] != 2 or not (p.shape == (2,) or p.shape == w.shape):
        return _lever_parts_numpy(w, p, L)  # one point: numpy's scalar complex arithmetic rounds differently
    k = _compiled()
    S = w.shape[:-1]
    mu = np.empty(S)
    nu = np.empty(S, complex)
    k._lever_parts_kernel(k.kernel_array(w).reshape(-1, 2), k.kernel_array(p).reshape(-1, 2), float(L),
                          mu.reshape(-1), nu.reshape(-1).view(float).reshape(-1, 2))
    return mu[()], nu[()]


def _lever_parts_numpy(w: np.ndarray, p: np.ndarray, L: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lever_parts` in numpy: the reference of the compiled path."""
    w, p = np.asarray(w, float), np.asarray(p, float)
    dy, dz = p[..., 0] - w[..., 0], p[..., 1] - w[..., 1]
    rho2 = dy * dy + dz * dz
    rho = np.sqrt(rho2)
    nc2 = (dz - 1j * dy) ** 2 / rho2
    return 1.0 - L / (2.0 * rho), -(L / (2.0 * rho)) * nc2


def lever_wrist(x: np.ndarray, p: np.ndarray, L: float) -> np.ndarray:
    """The unique wrist that puts a straight shaft's tip at ``x`` through port ``p``."""
    x, p = np.asarray(x, float), np.asarray(p, float)
    d = x - p
    return x - L * d / _norm(d)[..., None]


# ----------------------------------------------------------------------------- flexed beam
def _solve_length(d: np.ndarray, s_of) -> np.ndarray:
    """``x`` with ``x^2 (1 + s(x)^2) = d^2`` by Newton's method from ``x = d``; ``s_of(x)`` returns
    ``s`` and ``ds/dx`` (P2 eq. 18 and its tip-side twin)."""
    x = np.array(d, dtype=float, copy=True)
    for _ in range(_NEWTON_ITERS):
        s, ds = s_of(x)
        g = 1.0 + s * s
        x = x - (x * x * g - d * d) / (2.0 * x * g + 2.0 * x * x * s * ds)
    return x


def _solve_a(rho: np.ndarray, L: float, t: np.ndarray) -> np.ndarray:
    """Port position ``a`` along the chord from ``rho^2 = a^2 (1 + (t b^2/3)^2)``, b = L - a (P2 eq. 18)."""
    return _solve_length(rho, lambda a: (t * (L - a) ** 2 / 3.0, -2.0 * t * (L - a) / 3.0))


def _solve_b(r: np.ndarray, L: float, t: np.ndarray) -> np.ndarray:
    """Tip-side length ``b = L - a`` from the tip->port distance ``r^2 = b^2 (1 + (t a b/3)^2)``."""
    return _solve_length(r, lambda b: (t * (L - b) * b / 3.0, t * (L - 2.0 * b) / 3.0))


def flexed_geometry(w: np.ndarray, p: np.ndarray, L: float, t) -> dict[str, np.ndarray]:
    """Shape of the flexed shaft for wrist ``w``, port ``p`` and load ``t``.

    Returns a dict with ``rho`` (|p - w|), ``theta`` (angle of p - w), ``a``, ``b``, ``phi``
    (chord angle) and ``tip``.

    Planar (d = 2): compiled, one pass over the batch (:func:`.compiled._geometry2_kernel`), the same operations in
    the same order as :func:`_flexed_geometry_numpy` (the reference), so the same values to the last bit.
    """
    w, p = np.asarray(w, float), np.asarray(p, float)
    t = np.asarray(t, float)
    flat = _planar_batch(w, p, t)
    if flat is None:
        return _flexed_geometry_numpy(w, p, L, t)
    S, W, P, T = flat
    n = len(T)
    O = np.empty((7, n))
    _compiled()._geometry2_kernel(W, P, float(L), T, bool(np.any(t != 0)), O)
    tip = O[5:7].T.reshape(S + (2,))
    rho, theta, a, b, phi = (O[i].reshape(S)[()] for i in range(5))
    return {"rho": rho, "theta": theta, "a": a, "b": b, "phi": phi, "tip": tip}


def _flexed_geometry_numpy(w: np.ndarray, p: np.ndarray, L: float, t) -> dict[str, np.ndarray]:
    """:func:`flexed_geometry` in numpy: the reference of the compiled planar path."""
    w, p = np.asarray(w, float), np.asarray(p, float)
    t = np.asarray(t, float)
    d = p - w
    rho = _norm(d)
    theta = angle_of(d)
    a = _solve_a(rho, L, t) if np.any(t != 0) else rho + 0.0 * t
    b = L - a
    phi = theta + np.arctan(t * b * b / 3.0)
    tip = w + L * direction(phi)
    return {"rho": rho, "theta": theta, "a": a, "b": b, "phi": phi, "tip": tip}


# ----------------------------------------------------------------------------- compiled planar shaft
# The planar flexed shaft per element in compiled loops: the numpy functions' operations in the same
# order (IEEE arithmetic, no fast-math; sin, cos, atan and atan2 are the C library's, as numpy's), so the
# same bits. A batch runs compiled only when every output has the batch's full shape (the common case);
# otherwise the numpy reference runs, which keeps the shapes of its outputs.
def _planar_batch(a: np.ndarray, b: np.ndarray, t: np.ndarray):
    """``(S, A (n, 2), B (n, 2), T (n,))`` C arrays over the broadcast batch shape ``S`` of two planar
    point arrays and a load, or None when not planar or when ``t`` would widen the points' batch."""
    if a.shape[-1:] != (2,) or b.shape[-1:] != (2,):
        return None
    S = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    if np.broadcast_shapes(S, t.shape) != S:
        return None
    return S, _flat(a, S + (2,)).reshape(-1, 2), _flat(b, S + (2,)).reshape(-1, 2), _flat(t, S).reshape(-1)


def _flat(a: np.ndarray, shape: tuple) -> np.ndarray:
    if a.shape != shape:
        a = np.broadcast_to(a, shape)
    return _compiled().kernel_array(a)


def flexed_tip(w: np.ndarray, p: np.ndarray, L: float, t) -> np.ndarray:
    """Tip of the flexed shaft (P2 eqs. 6, 7, 10, 18); in space ``t`` is the world load vector."""
    if np.shape(w)[-1] == 3:
        if np.shape(w) == (3,) and np.shape(p) == (3,) and np.shape(t) == (3,):
            try:
                return _spatial_tip1(w, p, float(L), t)
            except (ZeroDivisionError, OverflowError, ValueError):  # numpy's inf/nan (and warnings) below
                pass
        return _spatial_geometry(w, p, L, t)["tip"]
    return flexed_geometry(w, p, L, t)["tip"]


def _spatial_tip1(w, p, L: float, t) -> np.ndarray:
    """:func:`_spatial_geometry`'s tip for one wrist, port and load, in plain floats: the same operations
    in the same order (numpy's sums of three terms add left to right; sqrt is exact; the trigonometry is
    the C library's, as numpy's without wide SIMD), the same bits; a simulation step calls it once per
    tip, where numpy's per-call cost was most of the calibration's time."""
    w0, w1, w2 = (float(v) for v in w)
    p0, p1, p2 = (float(v) for v in p)
    t0, t1, t2 = (float(v) for v in t)
    d0, d1, d2 = p0 - w0, p1 - w1, p2 - w2
    rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    u0, u1, u2 = d0 / rho, d1 / rho, d2 / rho
    tu = t0 * u0 + t1 * u1 + t2 * u2
    q0, q1, q2 = t0 - tu * u0, t1 - tu * u1, t2 - tu * u2
    tau = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
    if tau > 0:
        n0, n1, n2 = q0 / tau, q1 / tau, q2 / tau
        a = rho  # _solve_a: Newton from a = rho
        for _ in range(_NEWTON_ITERS):
            la = L - a
            s = tau * la ** 2 / 3.0
            ds = -2.0 * tau * la / 3.0
            g = 1.0 + s * s
            a = a - (a * a * g - rho * rho) / (2.0 * a * g + 2.0 * a * a * s * ds)
    else:
        n0 = n1 = n2 = 0.0
        a = rho
    b = L - a
    beta = math.atan(tau * b * b / 3.0)
    c, sn = math.cos(beta), math.sin(beta)
    return np.array([w0 + L * (c * u0 + sn * n0), w1 + L * (c * u1 + sn * n1), w2 + L * (c * u2 + sn * n2)])


def _spatial_geometry(w, p, L: float, t) -> dict[str, np.ndarray]:
    """The 3-D flexed shaft: wrist->port unit ``u``, bending normal ``n``, lateral load ``tau``,
    port position ``a`` along the chord, chord angle ``beta`` from ``u`` toward ``n``, ``tip``."""
    w, p = np.asarray(w, float), np.asarray(p, float)
    t = np.broadcast_to(np.asarray(t, float), np.broadcast_shapes(w.shape, p.shape))
    d = p - w
    rho = _norm(d)
    u = d / rho[..., None]
    tp = t - np.sum(t * u, axis=-1, keepdims=True) * u
    tau = _norm(tp)
    bent = tau > 0
    n = np.where(bent[..., None], tp / np.where(bent, tau, 1.0)[..., None], 0.0)
    a = np.where(bent, _solve_a(rho, L, np.where(bent, tau, 0.0)), rho)
    b = L - a
    beta = np.arctan(tau * b * b / 3.0)
    chord = np.cos(beta)[..., None] * u + np.sin(beta)[..., None] * n
    return {"rho": rho, "u": u, "n": n, "tau": tau, "a": a, "b": b, "beta": beta, "tip": w + L * chord}


def flexed_wrist_plane(x: np.ndarray, p: np.ndarray, L: float, tau, e2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3-D wrist putting the tip at ``x`` through port ``p`` with a lateral load of magnitude ``tau``
    bending the shaft in the plane of the port->tip line and the unit vector ``e2`` normal to it.

    Returns ``(w, t)``: the wrist and the world load vector ``t`` (normal to the wrist->port line,
    ``|t| = tau``) that reproduce ``x`` through :func:`flexed_tip`. The field kernels parametrize the
    load direction by the angle of ``e2`` around the port->tip line.
    """
    x, p = np.asarray(x, float), np.asarray(p, float)
    e2 = np.asarray(e2, float)
    tau = np.asarray(tau, float)
    e = x - p
    r = _norm(e)
    e1 = e / r[..., None]
    b = _solve_b(r, L, tau)
    a = L - b
    al = np.arctan(tau * a * b / 3.0)
    chord = np.cos(al)[..., None] * e1 - np.sin(al)[..., None] * e2
    w = x - L * chord
    u = (p - w) / _norm(p - w)[..., None]
    nt = chord - np.sum(chord * u, axis=-1, keepdims=True) * u
    nn = _norm(nt)
    t = np.where((nn > 0)[..., None], tau[..., None] * nt / np.where(nn > 0, nn, 1.0)[..., None], 0.0)
    return w, t


def flexed_jacobian(w: np.ndarray, p: np.ndarray, L: float, t) -> np.ndarray:
    """``d tip / d w`` (..., 2, 2) of the flexed shaft at constant port and ``t = Ft/EI``.

    ``J = I + L n_phi (d phi / d w)^T`` with ``d phi/d w = -n_theta/rho - beta'(a) a'(rho) u_theta``,
    ``beta = atan(t b^2/3)``. Equals :func:`lever_jacobian` at ``t = 0``.

    In space (``w`` (..., 3), ``t`` the world load vector): ``J = I + L d chord / d w`` with
    ``chord = cos(beta) u + sin(beta) n`` differentiated through ``u(w)``, ``n(w)`` (the normal part
    of the constant world ``t``), ``rho(w)`` and ``tau(w)`` (implicit in P2 eq. 18 for ``a``).
    """
    if np.shape(w)[-1] == 3:
        return _spatial_jacobian(w, p, L, t)
    w, p = np.asarray(w, float), np.asarray(p, float)
    t = np.asarray(t, float)
    flat = _planar_batch(w, p, t)
    if flat is None:
        return _flexed_jacobian2_numpy(w, p, L, t)
    S, W, P, T = flat
    J = np.empty((len(T), 2, 2))
    _compiled()._jacobian2_kernel(W, P, float(L), T, bool(np.any(t != 0)), J)
    return J.reshape(S + (2, 2))


def _flexed_jacobian2_numpy(w: np.ndarray, p: np.ndarray, L: float, t) -> np.ndarray:
    """The planar :func:`flexed_jacobian` in numpy: the reference of the compiled path."""
    g = _flexed_geometry_numpy(w, p, L, t)
    t = np.asarray(t, float)
    rho, a, b = g["rho"], g["a"], g["b"]
    u = direction(g["theta"])
    n = direction_derivative(g["theta"])
    n_phi = direction_derivative(g["phi"])
    s = t * b * b / 3.0
    gg = 1.0 + s * s
    dgg = -(4.0 * t * b / 3.0) * s
    beta_p = -(2.0 * t * b / 3.0) / gg
    a_p = 2.0 * rho / (2.0 * a * gg + a * a * dgg)
    grad_phi = -n / rho[..., None] - (beta_p * a_p)[..., None] * u
    eye = np.broadcast_to(np.eye(2), grad_phi.shape[:-1] + (2, 2))
    return eye + L * _outer(n_phi, grad_phi)


def _spatial_jacobian(w, p, L: float, t) -> np.ndarray:
    g = _spatial_geometry(w, p, L, t)
    t = np.broadcast_to(np.asarray(t, float), g["tip"].shape)
    u, n, rho, tau, a, b, beta = g["u"], g["n"], g["rho"], g["tau"], g["a"], g["b"], g["beta"]
    eye = np.eye(3)
    Du = -(eye - _outer(u, u)) / rho[..., None, None]
    ut = np.sum(u * t, axis=-1)
    tDu = np.einsum("...i,...ij->...j", t, Du)
    Dtp = -ut[..., None, None] * Du - _outer(u, tDu)
    dtau = np.einsum("...i,...ij->...j", n, Dtp)
    safe = np.where(tau > 0, tau, 1.0)
    Dn = (Dtp - _outer(n, dtau)) / safe[..., None, None]
    s = tau * b * b / 3.0
    gg = 1.0 + s * s
    dgg = -(4.0 * tau * b / 3.0) * s
    Fa = 2.0 * a * gg + a * a * dgg
    a_rho = 2.0 * rho / Fa
    a_tau = -(a * a * 2.0 * s * b * b / 3.0) / Fa
    beta_a = -(2.0 * tau * b / 3.0) / gg
    beta_tau = (b * b / 3.0) / gg + beta_a * a_tau
    dbeta = (beta_a * a_rho)[..., None] * (-u) + beta_tau[..., None] * dtau
    cb, sb = np.cos(beta)[..., None], np.sin(beta)[..., None]
    v = -sb * u + cb * n
    return eye + L * (_outer(v, dbeta) + cb[..., None] * Du + sb[..., None] * Dn)


def flexed_wrist(x: np.ndarray, p: np.ndarray, L: float, t) -> np.ndarray:
    """The wrist that puts the flexed shaft's tip at ``x`` through port ``p`` under load ``t``."""
    x, p = np.asarray(x, float), np.asarray(p, float)
    t = np.asarray(t, float)
    flat = _planar_batch(x, p, t)
    if flat is None:
        return _flexed_wrist_numpy(x, p, L, t)
    S, X, P, T = flat
    w = np.empty((len(T), 2))
    _compiled()._wrist2_kernel(X, P, float(L), T, bool(np.any(t != 0)), w)
    return w.reshape(S + (2,))


def _flexed_wrist_numpy(x: np.ndarray, p: np.ndarray, L: float, t) -> np.ndarray:
    """:func:`flexed_wrist` in numpy: the reference of the compiled planar path."""
    x, p = np.asarray(x, float), np.asarray(p, float)
    t = np.asarray(t, float)
    d = x - p
    r = _norm(d)
    if not np.any(t != 0):
        return x - L * d / r[..., None] + 0.0 * t[..., None]
    b = _solve_b(r, L, t)
    a = L - b
    phi = angle_of(d) - np.arctan(t * a * b / 3.0)
    return x - L * direction(phi)


def beam_slope(xm: np.ndarray, a: np.ndarray, L: float, fp_over_ei: np.ndarray) -> np.ndarray:
    """P2 eq. (2): slope ``y_m'(x_m)`` of the simply supported beam in model space."""
    b = L - a
    mac = np.where(xm >= a, (xm - a) ** 2, 0.0)
    return -(fp_over_ei / 6.0) * (L * b * (1 - b * b / L**2 - 3 * xm * xm / L**2) + 3 * mac)


def beam_height(xm: np.ndarray, a: np.ndarray, L: float, fp_over_ei: np.ndarray) -> np.ndarray:
    """P2 eq. (1): height ``y_m(x_m)`` of the simply supported beam in model space."""
    b = L - a
    mac = np.where(xm >= a, (xm - a) ** 3, 0.0)
    return -(fp_over_ei / 6.0) * (L * b * xm * (1 - b * b / L**2 - xm * xm / L**2) + mac)


def flexed_end_angles(w: np.ndarray, p: np.ndarray, L: float, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tip position and world tangent angles at the wrist and tip ends of the flexed shaft.

    These are the measurements P2's flexion controller is fed: ``(tip, theta_w, theta_t)``.
    """
    g = flexed_geometry(w, p, L, t)
    t = np.asarray(t, float)
    a = g["a"]
    fp = t * L / a
    s0 = beam_slope(np.zeros_like(a), a, L, fp)
    sL = beam_slope(np.full_like(a, L), a, L, fp)
    return g["tip"], g["phi"] + np.arctan(s0), g["phi"] + np.arctan(sL)


def estimate_from_ends(pw: np.ndarray, pt: np.ndarray, th_w: np.ndarray, th_t: np.ndarray, L: float) -> dict[str, np.ndarray]:
    """P2 eqs. (8)-(14): flexion-model parameters from end positions and orientations.

    Returns ``a``, ``fp_over_ei`` (Fp/EI), ``t`` (Ft/EI = Fp a / (EI L)), ``port`` (eq. 8) and
    ``phi``. Where the end slopes coincide (no measurable flexion) ``a`` is not identifiable:
    those entries are NaN.
    """
    pw, pt = np.asarray(pw, float), np.asarray(pt, float)
    phi = angle_of(pt - pw)
    s0 = np.tan(np.asarray(th_w, float) - phi)
    sL = np.tan(np.asarray(th_t, float) - phi)
    den = sL - s0
    with np.errstate(divide="ignore", invalid="ignore"):
        a = L * (2 * sL + s0) / den
        a = np.where(np.isfinite(a) & (den != 0), a, np.nan)  # equal slopes: not identifiable
        fp = 2 * (s0 - sL) / (a * (a - L))
        fp = np.where(np.isfinite(fp), fp, np.nan)
        ym = -fp * a * a * (a - L) ** 2 / (3 * L)
    port = pw + a[..., None] * direction(phi) + ym[..., None] * direction_derivative(phi)
    return {"a": a, "fp_over_ei": fp, "t": fp * a / L, "port": port, "phi": phi, "ym": ym}


# ----------------------------------------------------------------------------- P2's controller, d-generic
def flexed_end_directions(w: np.ndarray, p: np.ndarray, L: float, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tip position and unit end tangents (wrist->tip sense) of the flexed shaft: ``(tip, dw, dt)``.

    What P2's flexion controller measures, with directions as unit vectors (..., d) so that the plane
    (``d = 2``: ``direction`` of :func:`flexed_end_angles`) and space (``d = 3``: the tangents of the
    beam in its bending plane, P2 eq. 2 for the slopes) share one interface.
    """
    w = np.asarray(w, float)
    if w.shape[-1] == 2:
        tip, thw, tht = flexed_end_angles(w, p, L, t)
        return tip, direction(thw), direction(tht)
    g = _spatial_geometry(w, p, L, t)
    u, n, tau, a, beta, tip = g["u"], g["n"], g["tau"], g["a"], g["beta"], g["tip"]
    cb, sb = np.cos(beta)[..., None], np.sin(beta)[..., None]
    chord = cb * u + sb * n
    v = -sb * u + cb * n  # in the bending plane, normal to the chord, toward the bent side (0 unbent)
    fp = tau * L / a
    a0 = np.arctan(beam_slope(np.zeros_like(a), a, L, fp))[..., None]
    aL = np.arctan(beam_slope(np.full_like(a, L), a, L, fp))[..., None]
    return tip, np.cos(a0) * chord + np.sin(a0) * v, np.cos(aL) * chord + np.sin(aL) * v


def _chord_frame(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (..., 3) completing the unit chord ``c`` to a right-handed frame (the axis of
    least |component| as reference, deterministic)."""
    a = np.abs(c)
    ref = np.zeros_like(c)
    first = (a[..., 0] <= a[..., 1]) & (a[..., 0] <= a[..., 2])
    second = ~first & (a[..., 1] <= a[..., 2])
    ref[..., 0] = first
    ref[..., 1] = second
    ref[..., 2] = ~first & ~second
    f1 = np.cross(c, ref)
    f1 = f1 / _norm(f1)[..., None]
    return f1, np.cross(c, f1)


def bending_plane(pw: np.ndarray, pt: np.ndarray, dw: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bending plane P2's flexion controller estimates in 3-D from measured end poses.

    A shaft loaded only at its ends bends in one plane, spanned by the wrist->tip chord and the end
    tangents. The estimate keeps the measured chord ``c`` (positions) in the plane and takes the
    in-plane normal ``nb`` (unit, normal to ``c``) that best fits, in least squares, the tangents'
    components normal to the chord: the principal direction of ``sum e e^T`` over
    ``e = d - (d.c) c`` of both ends (closed form: half the angle of the 2x2 problem). Sign-free:
    ``-nb`` describes the same plane. Where the tangents do not leave the chord (no measurable
    flexion) any ``nb`` fits; the one returned is deterministic and the planar estimate there is
    unidentifiable anyway.

    Returns ``(c_hat, nb)`` (..., 3).
    """
    c = np.asarray(pt, float) - np.asarray(pw, float)
    c = c / _norm(c)[..., None]
    f1, f2 = _chord_frame(c)
    comps = []
    for d in (np.asarray(dw, float), np.asarray(dt, float)):
        comps.append((np.sum(d * f1, axis=-1), np.sum(d * f2, axis=-1)))
    s11 = sum(x * x for x, _ in comps)
    s22 = sum(y * y for _, y in comps)
    s12 = sum(x * y for x, y in comps)
    psi = 0.5 * np.arctan2(2.0 * s12, s11 - s22)
    nb = np.cos(psi)[..., None] * f1 + np.sin(psi)[..., None] * f2
    return c, nb


def estimate_from_end_poses(pw: np.ndarray, pt: np.ndarray, dw: np.ndarray, dt: np.ndarray, L: float) -> dict[str, np.ndarray]:
    """P2's flexion estimate from measured end poses, in the plane or in space (..., d).

    ``pw``, ``pt``: measured wrist and tip positions (m); ``dw``, ``dt``: measured unit shaft
    directions at the wrist and the tip (wrist->tip sense). In the plane this is
    :func:`estimate_from_ends` on the directions' angles. In space (docs/physics.md "P2's flexion
    controller in 3-D") the bending plane comes from :func:`bending_plane`, then P2's planar
    estimator (eqs. 8-14) runs in that plane's coordinates (``[y, z]`` = components along ``nb`` and
    the chord).

    Returns ``a``, ``fp_over_ei``, ``t`` (the signed in-plane Ft/EI), ``port`` (..., d) and ``load``:
    what :func:`flexed_jacobian` takes as its load, the scalar ``t`` in the plane and in space the
    world vector ``t n_u`` (1/m^2, ``n_u`` the in-plane normal of the wrist->port line), so the 3-D
    flexed shaft through the estimated port with that load is exactly P2's planar beam of the plane.
    Unidentifiable entries (equal end slopes) are NaN, as in the plane.
    """
    pw, pt = np.asarray(pw, float), np.asarray(pt, float)
    if pw.shape[-1] == 2:
        est = estimate_from_ends(pw, pt, angle_of(np.asarray(dw, float)), angle_of(np.asarray(dt, float)), L)
        est["load"] = est["t"]
        return est
    c, nb = bending_plane(pw, pt, dw, dt)
    dw, dt = np.asarray(dw, float), np.asarray(dt, float)
    thw = np.arctan2(np.sum(dw * nb, axis=-1), np.sum(dw * c, axis=-1))
    tht = np.arctan2(np.sum(dt * nb, axis=-1), np.sum(dt * c, axis=-1))
    r = _norm(pt - pw)
    zero = np.zeros_like(r)
    shape = np.broadcast_shapes(r.shape, thw.shape, tht.shape)
    pw2 = np.zeros(shape + (2,))
    pt2 = np.stack(np.broadcast_arrays(zero, r), axis=-1) + pw2
    est = estimate_from_ends(pw2, pt2, thw, tht, L)
    port2 = est["port"]
    port = pw + port2[..., 0:1] * nb + port2[..., 1:2] * c
    thp = angle_of(port2)
    n_u = np.cos(thp)[..., None] * nb - np.sin(thp)[..., None] * c  # dir'(theta_p) in the plane
    out = {k: est[k] for k in ("a", "fp_over_ei", "t", "ym")}
    out.update(port=port, load=est["t"][..., None] * n_u, chord=c, normal=nb)
    return out


def flexion_controller_jacobian(pw: np.ndarray, pt: np.ndarray, dw: np.ndarray, dt: np.ndarray, L: float) -> np.ndarray:
    """``Jhat_tw`` (..., d, d) of P2's flexion controller: the flexed-shaft ``d tip / d w`` at the
    measured wrist, holding the estimated port and load (:func:`estimate_from_end_poses`). NaN where
    the estimate is unidentifiable (the controller then falls back to the lever)."""
    est = estimate_from_end_poses(pw, pt, dw, dt, L)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        J = flexed_jacobian(np.asarray(pw, float), est["port"], L, est["load"])
    return J


def tilt(d: np.ndarray, delta: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Unit direction ``d`` (..., 3) turned by the angle ``|delta|`` (rad) toward
    ``delta[0] e1 + delta[1] e2`` (``e1``, ``e2`` unit, normal to ``d``): a direction measurement
    with angular noise ``delta`` (..., 2)."""
    delta = np.asarray(delta, float)
    ang = np.sqrt(delta[..., 0] ** 2 + delta[..., 1] ** 2)
    safe = np.where(ang > 0, ang, 1.0)
    k = (delta[..., 0:1] * e1 + delta[..., 1:2] * e2) / safe[..., None]
    return np.cos(ang)[..., None] * d + np.sin(ang)[..., None] * k
