"""The exact ``|phi_max|`` (the largest angle between a desired and the actual motion) of 2x2 and 3x3 motion
maps, and a direction attaining it (the package docstring says how the 3-D value is exact)."""
from __future__ import annotations

import math

from .basics import NAN, PI, _jit, _maxabs3x3
from .eigen import _cross_null, _eig2, _qform, _sym3_eigh, _sym3_eigvals, _sym3_top
from .singular import _gram


# ============================================================================ |phi_max| in the plane
@_jit
def phi_max2(M):
    """Exact ``|phi_max|`` of a 2x2 ``M``: ``min(pi, |arg mu| + asin(|nu|/|mu|))``, ``pi`` when
    ``|nu| >= |mu|`` (``metrics.phi_max``'s closed form)."""
    mr = 0.5 * (M[0, 0] + M[1, 1])
    mi = 0.5 * (M[1, 0] - M[0, 1])
    amu = math.hypot(mr, mi)
    anu = math.hypot(0.5 * (M[0, 0] - M[1, 1]), 0.5 * (M[0, 1] + M[1, 0]))
    if not amu > 0.0:
        return PI
    ratio = anu / amu
    if not ratio < 1.0:
        return PI
    return min(PI, abs(math.atan2(mi, mr)) + math.asin(ratio))


# ============================================================================ |phi_max| in 3-D
@_jit
def _angle(m00, m01, m02, m10, m11, m12, m20, m21, m22, x0, x1, x2):
    """Angle (rad, in [0, pi]) between ``x`` and ``M x``; NaN if ``M x = 0``."""
    y0 = m00 * x0 + m01 * x1 + m02 * x2
    y1 = m10 * x0 + m11 * x1 + m12 * x2
    y2 = m20 * x0 + m21 * x1 + m22 * x2
    c0 = x1 * y2 - x2 * y1
    c1 = x2 * y0 - x0 * y2
    c2 = x0 * y1 - x1 * y0
    cr = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    dt = x0 * y0 + x1 * y1 + x2 * y2
    if cr == 0.0 and dt == 0.0:
        return NAN
    return math.atan2(cr, dt)


@_jit
def _cubic_root_in(c2, c1, c0, lo, hi):
    """A root of ``p(l) = l^3 - c2 l^2 + c1 l - c0`` in ``[lo, hi]`` where ``p`` changes sign
    (either orientation): bisection, with a Newton step accepted whenever it stays inside."""
    neg_lo = ((lo - c2) * lo + c1) * lo - c0 < 0.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if not (lo < mid < hi):
            break
        for k in range(2):
            pm = ((mid - c2) * mid + c1) * mid - c0
            if pm == 0.0:
                return mid
            if (pm < 0.0) == neg_lo:
                lo = mid
            else:
                hi = mid
            if k == 0:  # Newton from the bisection point
                dp = (3.0 * mid - 2.0 * c2) * mid + c1
                nx = mid - pm / dp if dp != 0.0 else lo
                if not (lo < nx < hi):
                    break
                mid = nx
    return 0.5 * (lo + hi)


@_jit
def _reversal(m00, m01, m02, m10, m11, m12, m20, m21, m22, want_root):
    """Does ``M`` (normalised, max |entry| = 1) have a real eigenvalue ``<= 0`` (a direction
    reversed or annihilated)? Returns ``(found, lambda)``; ``lambda`` only if ``want_root``."""
    c2 = m00 + m11 + m22
    c1 = (m00 * m11 - m01 * m10) + (m00 * m22 - m02 * m20) + (m11 * m22 - m12 * m21)
    c0 = (m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20)
          + m02 * (m10 * m21 - m11 * m20))
    # p(l) = det(l I - M) = l^3 - c2 l^2 + c1 l - c0; p(0) = -det, p(-inf) = -inf.
    if c0 <= 0.0:  # det <= 0: a real eigenvalue in [-bound, 0] (Cauchy bound)
        if c0 == 0.0 or not want_root:
            return True, 0.0
        return True, _cubic_root_in(c2, c1, c0, -(1.0 + abs(c2) + abs(c1) + abs(c0)), 0.0)
    # det > 0: negative eigenvalues come in pairs; then p has its local maximum at la < 0 with
    # p(la) >= 0
    disc = c2 * c2 - 3.0 * c1
    if disc < 0.0:
        return False, 1.0
    la = (c2 - math.sqrt(disc)) / 3.0
    if not la < 0.0:
        return False, 1.0
    pa = ((la - c2) * la + c1) * la - c0
    if pa < 0.0:
        return False, 1.0
    if not want_root or pa == 0.0:
        return True, la
    return True, _cubic_root_in(c2, c1, c0, la, 0.0)


@_jit
def _acute_eval(SN00, SN01, SN02, SN11, SN12, SN22, AN00, AN01, AN02, AN11, AN12, AN22, c, sig):
    """At ``sigma = 1 - 2 s c``: ``R = 1 - 4 Phi(s) = sigma^2 - 2 (1 - sigma) lambda_N / c`` with
    ``lambda_N = lambda_min(H)``, ``H = sigma S_N - (1 - sigma)/(2c) A_N``; ``dR``, ``d2R``
    (eigenvalue perturbation theory, ``d2R = +inf`` at an exact double ``lambda_N``), the
    eigenvector's ``(a_N, b_N) = (x^T S_N x, x^T A_N x)`` and the eigen-decomposition."""
    w = 0.5 * (1.0 - sig) / c
    e = _sym3_eigh(sig * SN00 - w * AN00, sig * SN01 - w * AN01, sig * SN02 - w * AN02,
                   sig * SN11 - w * AN11, sig * SN12 - w * AN12, sig * SN22 - w * AN22)
    x0, x1, x2 = e[3], e[4], e[5]
    # H' = dH/dsigma = S_N + A_N / (2c); g = H' x
    ic = 0.5 / c
    D00, D01, D02 = SN00 + ic * AN00, SN01 + ic * AN01, SN02 + ic * AN02
    D11, D12, D22 = SN11 + ic * AN11, SN12 + ic * AN12, SN22 + ic * AN22
    g0 = D00 * x0 + D01 * x1 + D02 * x2
    g1 = D01 * x0 + D11 * x1 + D12 * x2
    g2 = D02 * x0 + D12 * x1 + D22 * x2
    aN = _qform(SN00, SN01, SN02, SN11, SN12, SN22, x0, x1, x2, x0, x1, x2)
    bN = _qform(AN00, AN01, AN02, AN11, AN12, AN22, x0, x1, x2, x0, x1, x2)
    lam = e[0]
    R = sig * sig - 2.0 * (1.0 - sig) * lam / c
    dR = 2.0 * (sig + ((2.0 * sig - 1.0) * aN - (1.0 - sig) * bN / c) / c)
    # lambda'' = -2 sum_j (x_j^T H' x)^2 / (l_j - l_0)
    c1 = e[6] * g0 + e[7] * g1 + e[8] * g2
    c2 = e[9] * g0 + e[10] * g1 + e[11] * g2
    gap1 = e[1] - lam
    gap2 = e[2] - lam
    curv = 0.0
    if c1 != 0.0:
        curv = curv + c1 * c1 / gap1 if gap1 > 0.0 else math.inf
    if c2 != 0.0:
        curv = curv + c2 * c2 / gap2 if gap2 > 0.0 else math.inf
    d2R = 2.0 + 4.0 * (aN + ic * bN) / c + 4.0 * (1.0 - sig) * curv / c
    return R, dR, d2R, aN, bN, e


@_jit
def _rq(c, aN, bN, sig):
    """Lower bound of ``R`` from a unit ``x``: ``r_x(sigma) = 1 - 4 q_x(s)`` (``q_x = s a - s^2 b``
    bounds ``Phi`` above since ``x^T (S - s A) x >= lambda_min``)."""
    u = 1.0 - sig
    return sig * sig - 2.0 * u * sig * aN / c + u * u * bN / (c * c)


@_jit
def _quad_lower(c, lo, a_l, b_l, hi, a_h, b_h):
    """``min over sigma in [lo, hi] of max(r_l, r_h)`` (two convex quadratics): a certified lower
    bound of ``min R`` on the bracket."""
    best = math.inf
    k2l = 1.0 + 2.0 * a_l / c + b_l / (c * c)  # sigma^2 coefficients (b / c^2 > 0)
    k2h = 1.0 + 2.0 * a_h / c + b_h / (c * c)
    for k in range(5):
        if k == 0:   # vertex of r_l: r = k2 s^2 + k1 s + k0
            sg = -(-2.0 * a_l / c - 2.0 * b_l / (c * c)) / (2.0 * k2l) if k2l > 0.0 else lo
        elif k == 1:
            sg = -(-2.0 * a_h / c - 2.0 * b_h / (c * c)) / (2.0 * k2h) if k2h > 0.0 else lo
        elif k == 2:  # r_l = r_h: sigma (2 c da + db) = db
            db = b_l - b_h
            den = 2.0 * c * (a_l - a_h) + db
            sg = db / den if den != 0.0 else lo
        elif k == 3:
            sg = lo
        else:
            sg = hi
        if not (lo <= sg <= hi):
            continue
        v = max(_rq(c, a_l, b_l, sg), _rq(c, a_h, b_h, sg))
        if v < best:
            best = v
    return best


@_jit
def _model_step(lo, R_l, d_l, k_l, hi, R_h, d_h, k_h):
    """``argmin over [lo, hi] of max(Q_l, Q_h)``, ``Q`` the second-order models of ``R`` at the
    bracket ends: at a kink (two eigen-branches crossing) the crossing of the two branch models,
    which converges quadratically; for one smooth branch about the Newton point."""
    best = math.inf
    arg = 0.5 * (lo + hi)
    # Q_l(x) = R_l + d_l (x - lo) + k_l/2 (x - lo)^2 ; Q_h likewise around hi
    # Q_l - Q_h = A x^2 + B x + C
    A = 0.5 * (k_l - k_h)
    B = d_l - k_l * lo - d_h + k_h * hi
    C = (R_l - d_l * lo + 0.5 * k_l * lo * lo) - (R_h - d_h * hi + 0.5 * k_h * hi * hi)
    for k in range(5):
        if k == 0:
            x = lo - d_l / k_l if k_l > 0.0 else lo
        elif k == 1:
            x = hi - d_h / k_h if k_h > 0.0 else hi
        elif abs(A) <= 1e-12 * (abs(B) + 1e-300) * (hi - lo + 1e-300):
            if k == 3 or B == 0.0:
                continue
            x = -C / B
        else:
            disc = B * B - 4.0 * A * C
            if disc < 0.0:
                continue
            sq = math.sqrt(disc)
            q = -0.5 * (B + sq) if B >= 0.0 else -0.5 * (B - sq)
            x = q / A if k == 2 else (C / q if q != 0.0 else lo)
        if not (lo < x < hi):
            continue
        v = max(R_l + d_l * (x - lo) + 0.5 * k_l * (x - lo) ** 2,
                R_h + d_h * (x - hi) + 0.5 * k_h * (x - hi) ** 2)
        if v < best:
            best = v
            arg = x
    return arg


ACUTE_RTOL = 1e-14  # stop when the certified gap (or the Newton decrement) is below this * R


@_jit
def _acute(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22):
    """|phi_max| when ``S >= 0`` (no obtuse angle). ``sin^2 phi_max = min over sigma < 1 of R``,
    ``R(sigma) = 1 - 4 Phi(s)``, ``Phi(s) = s lambda_min(S - s A)`` concave, ``sigma = 1 - 2 s c``,
    evaluated on ``N = M - c I`` (``c = tr M / 3``) so that nothing cancels for ``M`` near ``c I``.

    Safeguarded Newton on the convex ``R`` (bracket ``[lo, hi]`` with ``R'(lo) < 0 < R'(hi)``);
    where two eigen-branches cross, ``R`` has a kink and the step is the crossing of the two
    quadratic lower bounds ``r_x`` at the bracket ends instead. Returns ``(angle, x0, x1, x2)``.
    """
    c = (m00 + m11 + m22) / 3.0
    if not c > 0.0:  # S >= 0 with trace 0: S = 0, every angle is pi/2
        return 0.5 * PI, 1.0, 0.0, 0.0
    n00, n11, n22 = m00 - c, m11 - c, m22 - c
    SN00, SN11, SN22 = n00, n11, n22
    SN01, SN02, SN12 = S01, S02, S12
    AN00, AN01, AN02, AN11, AN12, AN22 = _gram(n00, m01, m02, m10, n11, m12, m20, m21, n22)  # N^T N, N = M - c I
    # sigma = 0 is s = 1 / 2c, exact for M = c I. R'(1) >= 0 (slope lambda_min(S) >= 0 at s = 0).
    sig = 0.0
    R, dR, d2R, aN, bN, e = _acute_eval(SN00, SN01, SN02, SN11, SN12, SN22,
                                        AN00, AN01, AN02, AN11, AN12, AN22, c, sig)
    best_R, best_sig, best_e = R, sig, e
    lo, hi = -math.inf, 1.0          # lo unknown until some R' < 0; hi = 1 not evaluated yet
    have_l, have_h = False, False
    a_l = b_l = a_h = b_h = 0.0
    R_l = d_l = k_l = R_h = d_h = k_h = 0.0
    prev_dR = 0.0
    for it in range(60):
        kk = d2R if d2R < math.inf else 1e300
        if dR < 0.0:
            lo, a_l, b_l, have_l = sig, aN, bN, True
            R_l, d_l, k_l = R, dR, kk
        else:
            hi, a_h, b_h, have_h = sig, aN, bN, True
            R_h, d_h, k_h = R, dR, kk
        if dR == 0.0:
            break
        # smooth convergence: Newton decrement R'^2 / 2R'' below tolerance
        if d2R < math.inf and dR * dR <= 2.0 * d2R * (ACUTE_RTOL * R + 1e-300):
            break
        if have_l and have_h:
            lb = _quad_lower(c, lo, a_l, b_l, hi, a_h, b_h)
            if best_R - lb <= ACUTE_RTOL * best_R + 1e-300:
                break
        # a Newton step that jumps across the minimum without shrinking R' much: a kink
        kink = dR * prev_dR < 0.0 and abs(dR) > 0.1 * abs(prev_dR)
        prev_dR = dR
        width = hi - lo
        step = -dR / d2R if d2R < math.inf else 0.0
        nxt = sig + step
        if not have_l:
            # move left; at most s *= 16 per step (sigma = 1 - 2 s c)
            lim = 1.0 - 16.0 * (1.0 - sig)
            nxt = max(nxt, lim) if nxt < sig else lim
        elif not have_h:
            if not (nxt < 1.0):
                nxt = 0.5 * (sig + 1.0)
            if not nxt > sig:
                nxt = 0.5 * (sig + 1.0)
        else:
            if kink or not (lo < nxt < hi):
                nxt = _model_step(lo, R_l, d_l, k_l, hi, R_h, d_h, k_h)
                margin = 1e-9 * width
                if not (lo + margin < nxt < hi - margin):
                    nxt = 0.5 * (lo + hi)
        if nxt == sig:
            break
        sig = nxt
        R, dR, d2R, aN, bN, e = _acute_eval(SN00, SN01, SN02, SN11, SN12, SN22,
                                            AN00, AN01, AN02, AN11, AN12, AN22, c, sig)
        if R < best_R:
            best_R, best_sig, best_e = R, sig, e
    Rs = min(max(best_R, 0.0), 1.0)
    dual = math.atan2(math.sqrt(Rs), math.sqrt(1.0 - Rs))  # >= phi_max (best_R >= min R)
    e = best_e
    x0, x1, x2 = e[3], e[4], e[5]
    prim = _angle(m00, m01, m02, m10, m11, m12, m20, m21, m22, x0, x1, x2)
    if not prim >= dual - 1e-13:
        # a crossing of the two lowest eigen-branches at sigma*: the optimum mixes their
        # eigenvectors so that x^T S_N x = a_N* = c sigma* + 2 lambda_N(sigma*)
        y0, y1, y2 = e[6], e[7], e[8]
        target = c * best_sig + 2.0 * e[0]
        s00 = _qform(SN00, SN01, SN02, SN11, SN12, SN22, x0, x1, x2, x0, x1, x2)
        s01 = _qform(SN00, SN01, SN02, SN11, SN12, SN22, x0, x1, x2, y0, y1, y2)
        s11 = _qform(SN00, SN01, SN02, SN11, SN12, SN22, y0, y1, y2, y0, y1, y2)
        mm, rr, cs, sn = _eig2(s00, s01, s11)
        t = (target - (mm - rr)) / (2.0 * rr) if rr > 0.0 else 0.0
        t = min(1.0, max(0.0, t))
        ca, sa = math.sqrt(1.0 - t), math.sqrt(t)
        # f_hi = cs x + sn y (eigenvalue mm + rr), f_lo = cs y - sn x
        z0 = ca * (cs * y0 - sn * x0) + sa * (cs * x0 + sn * y0)
        z1 = ca * (cs * y1 - sn * x1) + sa * (cs * x1 + sn * y1)
        z2 = ca * (cs * y2 - sn * x2) + sa * (cs * x2 + sn * y2)
        pz = _angle(m00, m01, m02, m10, m11, m12, m20, m21, m22, z0, z1, z2)
        if pz > prim:
            prim, x0, x1, x2 = pz, z0, z1, z2
    return max(dual, prim), x0, x1, x2


@_jit
def _psi_eval(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22,
              A00, A01, A02, A11, A12, A22, y):
    """``psi(y) = tau lambda_max(-S, tau^2 I + A)`` (``tau = e^y``), ``F(y) = ln|M x| - y`` and
    the unit generalised eigenvector ``x``."""
    tau = math.exp(y)
    t2 = tau * tau
    p00, p11, p22 = A00 + t2, A11 + t2, A22 + t2
    # Cholesky P = L L^T
    l00 = math.sqrt(p00)
    l10 = A01 / l00
    l20 = A02 / l00
    l11 = math.sqrt(max(p11 - l10 * l10, 0.0))
    l21 = (A12 - l20 * l10) / l11
    l22 = math.sqrt(max(p22 - l20 * l20 - l21 * l21, 0.0))
    # K = L^-1 (lower triangular)
    k00 = 1.0 / l00
    k11 = 1.0 / l11
    k22 = 1.0 / l22
    k10 = -l10 * k00 * k11
    k21 = -l21 * k11 * k22
    k20 = -(l20 * k00 + l21 * k10) * k22
    # T = K (-S)
    t00 = -(k00 * S00)
    t01 = -(k00 * S01)
    t02 = -(k00 * S02)
    t10 = -(k10 * S00 + k11 * S01)
    t11 = -(k10 * S01 + k11 * S11)
    t12 = -(k10 * S02 + k11 * S12)
    t20 = -(k20 * S00 + k21 * S01 + k22 * S02)
    t21 = -(k20 * S01 + k21 * S11 + k22 * S12)
    t22 = -(k20 * S02 + k21 * S12 + k22 * S22)
    # C = T K^T (symmetric)
    c00 = t00 * k00
    c01 = t00 * k10 + t01 * k11
    c02 = t00 * k20 + t01 * k21 + t02 * k22
    c11 = t10 * k10 + t11 * k11
    c12 = t10 * k20 + t11 * k21 + t12 * k22
    c22 = t20 * k20 + t21 * k21 + t22 * k22
    mu, z0, z1, z2 = _sym3_top(c00, c01, c02, c11, c12, c22)
    # x = K^T z
    x0 = k00 * z0 + k10 * z1 + k20 * z2
    x1 = k11 * z1 + k21 * z2
    x2 = k22 * z2
    n = 1.0 / math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    x0 *= n
    x1 *= n
    x2 *= n
    y0 = m00 * x0 + m01 * x1 + m02 * x2
    y1 = m10 * x0 + m11 * x1 + m12 * x2
    y2 = m20 * x0 + m21 * x1 + m22 * x2
    F = 0.5 * math.log(y0 * y0 + y1 * y1 + y2 * y2) - y
    return tau * mu, F, x0, x1, x2


OBTUSE_STEP = 0.25  # the walk's step in y = ln tau where no bound allows a longer one


@_jit
def _look(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22,
          A00, A01, A02, A11, A12, A22, y, best, bang, bx0, bx1, bx2):
    """``psi`` and ``F`` at ``y``, with the largest ``psi`` and the largest angle (and its direction) seen
    so far updated: ``(P, F, best, bang, bx0, bx1, bx2)``."""
    P, F, x0, x1, x2 = _psi_eval(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22, A00, A01, A02, A11, A12, A22, y)
    a = _angle(m00, m01, m02, m10, m11, m12, m20, m21, m22, x0, x1, x2)
    if a > bang:
        bang, bx0, bx1, bx2 = a, x0, x1, x2
    return P, F, max(best, P), bang, bx0, bx1, bx2


@_jit
def _skip(best, P):
    """Distance from a point with ``psi = P`` within which no local maximum of ``psi`` can exceed
    ``best``: ``psi(y) >= psi(y_m) sech(y - y_m)`` at every local maximum ``y_m``."""
    if P > 0.0 and best > P:
        return math.acosh(best / P)
    return 0.0


@_jit
def _refine(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22,
            A00, A01, A02, A11, A12, A22, yp, Fp, yq, Fq, best, bang, bx0, bx1, bx2):
    """Root of ``F`` in ``[yp, yq]`` (``F(yp) > 0 >= F(yq)``: a local maximum of ``psi``) by
    regula falsi with the Anderson-Bjorck correction (superlinear also where ``F`` has a nearly
    double root, next to a reversal). Keeps the largest ``psi`` (for the bounds) and the direction
    with the largest angle (the value: near ``pi``, ``psi -> 1/2`` only resolves ~1e-8 rad).
    Returns ``(best, bang, x0, x1, x2)``."""
    side = 0
    stale = 0
    y_last = math.inf
    for _ in range(100):
        if Fq == 0.0 or yq - yp <= 1e-13 * (1.0 + abs(yp)):
            break
        ym = yp + (yq - yp) * Fp / (Fp - Fq)
        if not (yp < ym < yq):
            ym = 0.5 * (yp + yq)
        if abs(ym - y_last) <= 1e-13 * (1.0 + abs(ym)):
            break
        y_last = ym
        Pm, Fm, q0, q1, q2 = _psi_eval(m00, m01, m02, m10, m11, m12, m20, m21, m22,
                                       S00, S01, S02, S11, S12, S22,
                                       A00, A01, A02, A11, A12, A22, ym)
        if Pm > best:
            best = Pm
        am = _angle(m00, m01, m02, m10, m11, m12, m20, m21, m22, q0, q1, q2)
        if am > bang + 1e-15:
            stale = 0
        else:
            stale += 1
            if stale == 3:  # F at its rounding floor (near-singular maps): nothing left to gain
                break
        if am > bang:
            bang, bx0, bx1, bx2 = am, q0, q1, q2
        if abs(Fm) <= 1e-14:
            break
        if Fm > 0.0:
            if side == 1:   # yq kept twice: Anderson-Bjorck scaling
                g = 1.0 - Fm / Fp
                Fq *= g if g > 0.0 else 0.5
            yp, Fp = ym, Fm
            side = 1
        else:
            if side == -1:
                g = 1.0 - Fm / Fq
                Fp *= g if g > 0.0 else 0.5
            yq, Fq = ym, Fm
            side = -1
    return best, bang, bx0, bx1, bx2


@_jit
def _obtuse(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22,
            A00, A01, A02, A11, A12, A22, y_lo, y_hi):
    """|phi_max| when some angle is obtuse: ``cos phi_max = -2 max_y psi(y)`` over
    ``[y_lo, y_hi]`` (``y_lo <= ln sigma_min``, ``y_hi >= ln sigma_max``, where every local
    maximum lies). Returns ``(angle, x0, x1, x2)``.

    Local maxima of ``psi`` are the down-crossings of ``F``, each refined by Illinois. ``F`` falls
    with slope at most 1, so where ``F(y) > 0`` no maximum lies in ``[y, y + F)`` and where
    ``F(y) < 0`` none in ``(y + F, y]``; with the sech bound (``_skip``) these set the walk's
    steps, and ``OBTUSE_STEP`` where both are shorter. A walk from the right end stops at its
    first down-crossing; the walk from the left end covers the rest.
    """
    best = -1.0                # largest psi seen (for the bounds)
    bang = -1.0                # largest angle seen and its direction (the value)
    bx0 = bx1 = bx2 = 0.0
    yr = y_hi
    Pr, Fr, best, bang, bx0, bx1, bx2 = _look(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22,
                                              A00, A01, A02, A11, A12, A22, yr, best, bang, bx0, bx1, bx2)
    for _ in range(1000):
        if not Fr < 0.0 or yr <= y_lo:
            break
        step = max(-Fr, _skip(best, Pr), OBTUSE_STEP)
        yn = max(yr - step, y_lo)
        Pn, Fn, best, bang, bx0, bx1, bx2 = _look(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22,
                                                  A00, A01, A02, A11, A12, A22, yn, best, bang, bx0, bx1, bx2)
        if Fn > 0.0:
            best, bang, bx0, bx1, bx2 = _refine(m00, m01, m02, m10, m11, m12, m20, m21, m22,
                                                S00, S01, S02, S11, S12, S22, A00, A01, A02, A11,
                                                A12, A22, yn, Fn, yr, Fr, best, bang, bx0, bx1, bx2)
        yr, Fr, Pr = yn, Fn, Pn
    # walk from the left end up to yr (where F(yr) >= 0, or yr = y_lo)
    y = y_lo
    if y < yr:
        P, F, best, bang, bx0, bx1, bx2 = _look(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22,
                                                A00, A01, A02, A11, A12, A22, y, best, bang, bx0, bx1, bx2)
        for _ in range(4000):
            step = max(F, _skip(best, P), OBTUSE_STEP)
            yn = y + step
            if yn >= yr:
                # F(yr) >= 0: a down-crossing in [y, yr] needs an up-crossing too, i.e. two
                # extrema within one step; with F(y) > 0 none lies in [y, y + F)
                break
            Pn, Fn, n0, n1, n2 = _psi_eval(m00, m01, m02, m10, m11, m12, m20, m21, m22,
                                           S00, S01, S02, S11, S12, S22,
                                           A00, A01, A02, A11, A12, A22, yn)
            best = max(best, Pn)
            a = _angle(m00, m01, m02, m10, m11, m12, m20, m21, m22, n0, n1, n2)
            if a > bang:
                bang, bx0, bx1, bx2 = a, n0, n1, n2
            if F > 0.0 and Fn <= 0.0:
                best, bang, bx0, bx1, bx2 = _refine(m00, m01, m02, m10, m11, m12, m20, m21,
                                                    m22, S00, S01, S02, S11, S12, S22, A00, A01,
                                                    A02, A11, A12, A22, y, F, yn, Fn, best, bang,
                                                    bx0, bx1, bx2)
            y, F, P = yn, Fn, Pn
    # For the generalised eigenvector x(y): angle(x, M x) >= acos(-2 psi(y)) (AM-GM on
    # tau^2 + |Mx|^2), with equality at the maximum. The best primal angle (atan2, accurate also
    # near pi) is the value; the dual one only stands in if rounding made every direction useless.
    if not math.isnan(bang) and bang >= 0.0:
        return bang, bx0, bx1, bx2
    return math.acos(max(-1.0, -2.0 * best)), bx0, bx1, bx2


@_jit
def _phi_max3(M, want_dir):
    """``(angle, x0, x1, x2)``: exact ``|phi_max|`` and a direction attaining it."""
    s = _maxabs3x3(M)
    if math.isnan(s):
        return NAN, NAN, NAN, NAN
    if s == 0.0:
        return PI, 1.0, 0.0, 0.0
    r = 1.0 / s
    m00, m01, m02 = M[0, 0] * r, M[0, 1] * r, M[0, 2] * r
    m10, m11, m12 = M[1, 0] * r, M[1, 1] * r, M[1, 2] * r
    m20, m21, m22 = M[2, 0] * r, M[2, 1] * r, M[2, 2] * r
    rev, lam = _reversal(m00, m01, m02, m10, m11, m12, m20, m21, m22, want_dir)
    if rev:
        x0 = x1 = x2 = 0.0
        if want_dir:
            x0, x1, x2 = _cross_null(m00 - lam, m01, m02, m10, m11 - lam, m12, m20, m21, m22 - lam)
            if x0 == 0.0 and x1 == 0.0 and x2 == 0.0:
                x0 = 1.0
        return PI, x0, x1, x2
    S00, S11, S22 = m00, m11, m22
    S01 = 0.5 * (m01 + m10)
    S02 = 0.5 * (m02 + m20)
    S12 = 0.5 * (m12 + m21)
    smin_S = _sym3_eigvals(S00, S01, S02, S11, S12, S22)[0]
    if smin_S >= 0.0:
        return _acute(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22)
    A00, A01, A02, A11, A12, A22 = _gram(m00, m01, m02, m10, m11, m12, m20, m21, m22)  # M^T M
    det = (m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20)
           + m02 * (m10 * m21 - m11 * m20))
    # every local maximum of psi lies at y = ln|M x| in [ln sigma_min, ln sigma_max]: bounds from
    # the eigenvalues of A (padded by their rounding) and sigma_min >= |det| / ||M||_F^2
    f2 = A00 + A11 + A22
    a0, _a1, a2 = _sym3_eigvals(A00, A01, A02, A11, A12, A22)
    pad = 1e-12 * f2
    y_hi = 0.5 * math.log(min(a2 + pad, f2))
    lo2 = max(a0 - pad, (det / f2) ** 2)
    y_lo = 0.5 * math.log(lo2)
    return _obtuse(m00, m01, m02, m10, m11, m12, m20, m21, m22, S00, S01, S02, S11, S12, S22,
                   A00, A01, A02, A11, A12, A22, y_lo, y_hi)


@_jit
def phi_max3(M):
    """Exact ``|phi_max| = max over unit v in S^2 of angle(v, M v)`` (rad) of a 3x3 ``M``.

    ``pi`` when ``M`` has a real eigenvalue ``<= 0`` (also for ``M = 0``); NaN for a non-finite
    ``M``. Independent of positive scaling of ``M`` (hence of the gain).
    """
    return _phi_max3(M, False)[0]


@_jit
def p_phi3(M, out3):
    """Unit desired direction (up to sign) attaining ``phi_max3(M)``, written into ``out3``;
    returns the angle it attains (equal to ``phi_max3(M)`` to ~1e-9)."""
    v, x0, x1, x2 = _phi_max3(M, True)
    out3[0], out3[1], out3[2] = x0, x1, x2
    if math.isnan(v):
        return NAN
    if v == PI:
        return PI
    r = 1.0 / _maxabs3x3(M)
    return _angle(M[0, 0] * r, M[0, 1] * r, M[0, 2] * r, M[1, 0] * r, M[1, 1] * r, M[1, 2] * r,
                  M[2, 0] * r, M[2, 1] * r, M[2, 2] * r, x0, x1, x2)
