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

import numpy as np

from .arm import angle_of, direction, direction_derivative

_NEWTON_ITERS = 8


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
    as a complex number ``n_c = (dz - i dy)/rho``. No trigonometry: the fields' fast path.
    """
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
    """
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


def flexed_tip(w: np.ndarray, p: np.ndarray, L: float, t) -> np.ndarray:
    """Tip of the flexed shaft (P2 eqs. 6, 7, 10, 18); in space ``t`` is the world load vector."""
    if np.shape(w)[-1] == 3:
        return _spatial_geometry(w, p, L, t)["tip"]
    return flexed_geometry(w, p, L, t)["tip"]


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
    g = flexed_geometry(w, p, L, t)
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
