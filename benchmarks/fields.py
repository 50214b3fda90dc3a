"""Speed of ``errplan fields`` against plain vectorized numpy, planar and spatial (issues 2 and 10).

    python benchmarks/fields.py [--repeat 3] [--quick]
    python benchmarks/fields.py --scale [--repeat 3]     # issue 21's problems at scale only
    python benchmarks/fields.py --where [--repeat 3]     # where their CPU time goes (start-up, search, lanes)

With ``--scale`` (issue 21): planar 0.25 mm over P1's workspace with the 5 x 5 port box against the
chunked elementwise planar peer with reachability, and the PHANToM 1.5 task region at 2 mm with
3 x 3 x 3 ports against the chunked elementwise spatial peer; errplan's whole process, errplan in
process (all cores) and the peer alternately, medians; CPU ns per (tip x sampled instance) of each;
targets: planar whole process <= 0.15 x peer, spatial <= 0.35 x peer. Also the rho* field (planar,
``--rho-res``, 0.5 mm by default) against a numpy peer doing a golden-section search over the gain on
the sampled worst case, and an estimate of the machine's limit (the peer's arithmetic of one instance
compiled into a tight loop on one core, :func:`machine_limit`).

Each row is measured in this one run, side by side, on this machine:

(a) planar: the whole ``errplan fields`` process (a subprocess, wall clock: interpreter start,
    imports, compiled-kernel cache load, scenario, worst case with local refinement, npz written)
    for a 1 mm grid of P1's workspace with a 5 x 5 port box (beasley2004_port.toml plus port_y,
    port_z +-10 mm); against (b) a plain vectorized numpy worst-case ||G|| alone on the same grid:
    per box instance the lever wrist of every tip, the lever Jacobians, ``G = I - k J Jhat^-1`` and
    the closed-form largest singular value ``sqrt((f + sqrt(f^2 - 4 det^2)) / 2)``; no refinement,
    no |phi_max|, no reachability. Twice: with stacked 2 x 2 matrices (``np.linalg.inv``, ``@``:
    issue 2's baseline with the SVD replaced) and written out elementwise (the strongest plain
    peer). Target: (a) <= (b) / 2.
(c) spatial: the whole ``errplan fields --metrics G_norm`` process for a 4 mm grid of a task region of
    the bundled PHANToM 1.5 (scenarios/phantom15_spatial.toml) with a 3 x 3 x 3 port sample; against (d) plain numpy
    worst-case sigma_max over the same grid and sample, skipping arm reachability: stacked 3 x 3
    lever Jacobians, ``np.linalg.inv``, ``G = I - k J Jhat^-1`` and sigma_max from the closed-form
    (trigonometric) largest eigenvalue of G^T G; and the same written out elementwise (cofactor
    inverse, the six entries of G^T G: the strongest plain peer). Target: (c) <= (d) / 4.
(e) how the spatial time grows with grid points (resolution) and with error instances (samples per
    axis), and the speed-up from 1 to 2 workers (in-process compute, warm cache).
Also: the first run's compile cost (empty kernel cache) against a warm run.
"""
from __future__ import annotations

import argparse
import re
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PLANAR = REPO / "scenarios" / "beasley2004_port.toml"
BOX = 0.010
# --scale targets, whole process over the chunked elementwise peer (planar 0.25 mm, spatial 2 mm)
PLANAR_TARGET, SPATIAL_TARGET = 0.15, 0.35
RHO_RES = 0.0005  # the rho* row's planar grid: 0.5 mm (at 0.25 mm each side takes about 2 minutes a run here)
SPATIAL = REPO / "scenarios" / "phantom15_spatial.toml"


def planar_scenario(tmp: Path) -> Path:
    text = PLANAR.read_text(encoding="utf-8")
    unc = f"\n[uncertainty]\nport_y = [{-BOX}, {BOX}]\nport_z = [{-BOX}, {BOX}]\nsamples = 5\n"
    path = tmp / "bench_port_box.toml"
    path.write_text(text.replace("\n[sensors]", unc + "\n[sensors]", 1), encoding="utf-8")
    return path


def spatial_scenario(tmp: Path, res: float = 0.004, samples: int = 3) -> Path:
    """The bundled PHANToM 1.5 in 3-D (scenarios/phantom15_spatial.toml) with a pure port box (no tip load:
    the numpy peers model none), ``samples`` per axis, at ``res`` over its task region."""
    text = SPATIAL.read_text(encoding="utf-8")
    text = text.replace('urdf = "phantom15.urdf"', f'urdf = "{SPATIAL.parent / "phantom15.urdf"}"')
    text = re.sub(r"^tip_force_over_ei = .*$", "", text, flags=re.M)
    text = re.sub(r"^samples = .*$", f"samples = {samples}", text, flags=re.M)
    text = re.sub(r"^resolution = .*$", f"resolution = {res}", text, count=1, flags=re.M)
    path = tmp / f"spatial_{res}_{samples}.toml"
    path.write_text(text, encoding="utf-8")
    return path


def run_cli(args: list[str], env=None) -> float:
    cmd = [sys.executable, "-m", "errplan", "-q", "fields", *args]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"errplan fields failed: {r.stderr}")
    return dt


# ----------------------------------------------------------------------------- numpy baselines
def _lever(d, L):
    """The planar lever ``I - (L/rho)(I - u u^T)`` of wrist-to-port vectors ``d`` (n, 2), elementwise."""
    rho = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)
    s = L / rho
    u0, u1 = d[:, 0] / rho, d[:, 1] / rho
    return 1 - s + s * u0 * u0, s * u0 * u1, s * u0 * u1, 1 - s + s * u1 * u1


def _peer_g_norm(p, est, w, L, k):
    """The elementwise peer's ``||G||`` for the true port ``p``, the estimate and wrists ``w`` (n, 2):
    the 2 x 2 inverse written out and the closed-form largest singular value (inf where Jhat is singular)."""
    a, b, c, d = _lever(p - w, L)
    ha, hb, hc, hd = _lever(est - w, L)
    det = ha * hd - hb * hc
    sing = np.abs(det) < 1e-12
    det = np.where(sing, 1.0, det)
    ia, ib, ic, id_ = hd / det, -hb / det, -hc / det, ha / det
    g00 = 1 - k * (a * ia + b * ic)
    g01 = -k * (a * ib + b * id_)
    g10 = -k * (c * ia + d * ic)
    g11 = 1 - k * (c * ib + d * id_)
    f = g00 ** 2 + g01 ** 2 + g10 ** 2 + g11 ** 2
    dg = g00 * g11 - g01 * g10
    g = np.sqrt((f + np.sqrt(np.maximum(f * f - 4 * dg * dg, 0))) / 2)
    g[sing] = np.inf
    return g


def numpy_planar(y, z, est, L, k) -> tuple[np.ndarray, float]:
    t0 = time.perf_counter()
    X = np.stack(np.meshgrid(y, z, indexing="ij"), -1).reshape(-1, 2)
    est = np.asarray(est, float)
    worst = np.full(len(X), -np.inf)
    for dy in np.linspace(-BOX, BOX, 5):
        for dz in np.linspace(-BOX, BOX, 5):
            p = est + [dy, dz]
            e = X - p
            r = np.sqrt(e[:, 0] ** 2 + e[:, 1] ** 2)
            m = (r < L) & (r > 1e-9)
            x, e, r = X[m], e[m], r[m]
            w = x - L * e / r[:, None]
            g = _peer_g_norm(p, est, w, L, k)
            full = np.full(len(X), np.nan)
            full[m] = g
            worst = np.fmax(worst, full)
    return worst.reshape(len(y), len(z)), time.perf_counter() - t0


def numpy_planar_stacked(y, z, est, L, k) -> tuple[np.ndarray, float]:
    """The same worst case with stacked 2 x 2 matrices (``np.linalg.inv``, ``@``), as the baseline
    of issue 2 had it, with the closed-form singular value instead of a batched SVD."""
    t0 = time.perf_counter()
    X = np.stack(np.meshgrid(y, z, indexing="ij"), -1).reshape(-1, 2)
    est = np.asarray(est, float)

    def lever_jac(w, p):
        d = p - w
        rho = np.linalg.norm(d, axis=-1, keepdims=True)
        u = d / rho
        n = np.stack([u[..., 1], -u[..., 0]], -1)
        return u[..., :, None] * u[..., None, :] + (1 - L / rho)[..., None] * n[..., :, None] * n[..., None, :]

    worst = np.full(len(X), -np.inf)
    for dy in np.linspace(-BOX, BOX, 5):
        for dz in np.linspace(-BOX, BOX, 5):
            p = est + [dy, dz]
            r = np.linalg.norm(X - p, axis=-1)
            m = (r < L) & (r > 1e-9)
            x = X[m]
            w = x - L * (x - p) / r[m][:, None]
            J, Jh = lever_jac(w, p), lever_jac(w, est)
            sing = np.abs(np.linalg.det(Jh)) < 1e-12
            Jh[sing] = np.eye(2)
            G = np.eye(2) - k * J @ np.linalg.inv(Jh)
            f = np.einsum("...ij,...ij->...", G, G)
            dg = np.linalg.det(G)
            g = np.sqrt((f + np.sqrt(np.maximum(f * f - 4 * dg * dg, 0))) / 2)
            g[sing] = np.inf
            full = np.full(len(X), np.nan)
            full[m] = g
            worst = np.fmax(worst, full)
    return worst.reshape(len(y), len(z)), time.perf_counter() - t0


def sigma_max3_numpy(G: np.ndarray) -> np.ndarray:
    """Largest singular value of stacked 3 x 3 matrices: the trigonometric closed form of the
    largest eigenvalue of the symmetric G^T G."""
    A = np.einsum("...ki,...kj->...ij", G, G)
    q = np.trace(A, axis1=-2, axis2=-1) / 3
    p1 = A[..., 0, 1] ** 2 + A[..., 0, 2] ** 2 + A[..., 1, 2] ** 2
    p2 = (A[..., 0, 0] - q) ** 2 + (A[..., 1, 1] - q) ** 2 + (A[..., 2, 2] - q) ** 2 + 2 * p1
    p = np.sqrt(p2 / 6)
    ps = np.where(p > 0, p, 1.0)
    B = (A - q[..., None, None] * np.eye(3)) / ps[..., None, None]
    r = np.clip(np.linalg.det(B) / 2, -1, 1)
    lam = q + 2 * p * np.cos(np.arccos(r) / 3)
    return np.sqrt(np.maximum(lam, 0))


def numpy_spatial(axes, est, L, k, box, samples) -> tuple[np.ndarray, float]:
    t0 = time.perf_counter()
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    est = np.asarray(est, float)
    worst = np.full(len(X), -np.inf)
    I3 = np.eye(3)
    grids = [np.linspace(lo, hi, samples) for lo, hi in box]
    for dx in grids[0]:
        for dy in grids[1]:
            for dz in grids[2]:
                p = est + [dx, dy, dz]
                e = X - p
                r = np.sqrt(np.einsum("ij,ij->i", e, e))
                m = (r < L) & (r > 1e-9)
                e, r = e[m], r[m]
                u = e / r[:, None]
                w = X[m] - L * u
                J = I3 - (L / (L - r))[:, None, None] * (I3 - u[:, :, None] * u[:, None, :])
                d = est - w
                rho = np.sqrt(np.einsum("ij,ij->i", d, d))
                uh = d / rho[:, None]
                Jh = I3 - (L / rho)[:, None, None] * (I3 - uh[:, :, None] * uh[:, None, :])
                G = I3 - k * J @ np.linalg.inv(Jh)
                full = np.full(len(X), np.nan)
                full[m] = sigma_max3_numpy(G)
                worst = np.fmax(worst, full)
    return worst.reshape(tuple(len(a) for a in axes)), time.perf_counter() - t0


def numpy_spatial_elementwise(axes, est, L, k, box, samples) -> tuple[np.ndarray, float]:
    """The same worst case written out elementwise (the strongest plain peer): the 3 x 3 lever
    Jacobians entry by entry, the controller's inverse by cofactors, ``G^T G`` by its six distinct
    entries and its largest eigenvalue in the trigonometric closed form."""
    t0 = time.perf_counter()
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    est = np.asarray(est, float)
    worst = np.full(len(X), -np.inf)
    grids = [np.linspace(lo, hi, samples) for lo, hi in box]

    def lever(d0, d1, d2):  # I - (L/rho)(I - u u^T), entries
        rho = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        s = L / rho
        u = (d0 / rho, d1 / rho, d2 / rho)
        return [[(1 - s if i == j else 0.0) + s * u[i] * u[j] for j in range(3)] for i in range(3)]

    for dx in grids[0]:
        for dy in grids[1]:
            for dz in grids[2]:
                p = est + [dx, dy, dz]
                e0, e1, e2 = X[:, 0] - p[0], X[:, 1] - p[1], X[:, 2] - p[2]
                r = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                m = (r < L) & (r > 1e-9)
                e0, e1, e2, r = e0[m], e1[m], e2[m], r[m]
                w0, w1, w2 = X[m, 0] - L * e0 / r, X[m, 1] - L * e1 / r, X[m, 2] - L * e2 / r
                J = lever(p[0] - w0, p[1] - w1, p[2] - w2)
                H = lever(est[0] - w0, est[1] - w1, est[2] - w2)
                c00 = H[1][1] * H[2][2] - H[1][2] * H[2][1]
                c01 = H[1][2] * H[2][0] - H[1][0] * H[2][2]
                c02 = H[1][0] * H[2][1] - H[1][1] * H[2][0]
                det = H[0][0] * c00 + H[0][1] * c01 + H[0][2] * c02
                inv = [[c00, H[0][2] * H[2][1] - H[0][1] * H[2][2], H[0][1] * H[1][2] - H[0][2] * H[1][1]],
                       [c01, H[0][0] * H[2][2] - H[0][2] * H[2][0], H[0][2] * H[1][0] - H[0][0] * H[1][2]],
                       [c02, H[0][1] * H[2][0] - H[0][0] * H[2][1], H[0][0] * H[1][1] - H[0][1] * H[1][0]]]
                G = [[(1.0 if i == j else 0.0) - k * (J[i][0] * inv[0][j] + J[i][1] * inv[1][j] + J[i][2] * inv[2][j]) / det
                      for j in range(3)] for i in range(3)]
                A = {(i, j): G[0][i] * G[0][j] + G[1][i] * G[1][j] + G[2][i] * G[2][j]
                     for i in range(3) for j in range(i, 3)}
                q = (A[0, 0] + A[1, 1] + A[2, 2]) / 3
                p1 = A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2
                pp = np.sqrt(((A[0, 0] - q) ** 2 + (A[1, 1] - q) ** 2 + (A[2, 2] - q) ** 2 + 2 * p1) / 6)
                ps = np.where(pp > 0, pp, 1.0)
                b00, b11, b22 = (A[0, 0] - q) / ps, (A[1, 1] - q) / ps, (A[2, 2] - q) / ps
                b01, b02, b12 = A[0, 1] / ps, A[0, 2] / ps, A[1, 2] / ps
                detb = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
                lam = q + 2 * pp * np.cos(np.arccos(np.clip(detb / 2, -1, 1)) / 3)
                full = np.full(len(X), np.nan)
                full[m] = np.sqrt(np.maximum(lam, 0))
                worst = np.fmax(worst, full)
    return worst.reshape(tuple(len(a) for a in axes)), time.perf_counter() - t0


# ----------------------------------------------------------------------------- at scale (issue 21)
def chunked_planar_peer(y, z, est, L, k, arm, chunk=65536) -> tuple[np.ndarray, float]:
    """The elementwise planar peer (:func:`numpy_planar`) with reachability of every instance's
    wrist (``Arm.reachable``, vectorized numpy, both elbow branches inside the limits: the same
    robust validity errplan computes), over chunks of ``chunk`` tips (cache-sized arrays)."""
    t0 = time.perf_counter()
    X = np.stack(np.meshgrid(y, z, indexing="ij"), -1).reshape(-1, 2)
    est = np.asarray(est, float)
    out = np.empty(len(X))

    for c0 in range(0, len(X), chunk):
        Xc = X[c0:c0 + chunk]
        worst = np.full(len(Xc), -np.inf)
        for p, w, m in _peer_instances(Xc, est, L, arm):
            g = _peer_g_norm(p, est, w[m], L, k)
            full = np.full(len(Xc), np.nan)  # an unreachable instance invalidates the tip
            full[m] = g
            worst = np.maximum(worst, full)
        out[c0:c0 + chunk] = worst
    return out.reshape(len(y), len(z)), time.perf_counter() - t0


def _peer_instances(Xc, est, L, arm):
    """The planar peers' port instances (the 5 x 5 box around ``est``): for each, the true port ``p``, the
    lever wrists ``w`` (n, 2) of the tips ``Xc`` and where the instance is valid ``m`` (the shaft reaches
    the tip through the port and the arm reaches the wrist)."""
    for dy in np.linspace(-BOX, BOX, 5):
        for dz in np.linspace(-BOX, BOX, 5):
            p = est + [dy, dz]
            e = Xc - p
            r = np.sqrt(e[:, 0] ** 2 + e[:, 1] ** 2)
            m = (r < L) & (r > 1e-9)
            w = Xc - L * e / np.where(m, r, 1.0)[:, None]
            yield p, w, m & np.asarray(arm.reachable(w), bool)


def _peer_motion_map(p, est, w, L):
    """The elementwise peer's ``M = J Jhat^-1`` (entries m00, m01, m10, m11) for the true port ``p``,
    the estimate and wrists ``w`` (n, 2); NaN where Jhat is singular."""
    a, b, c, d = _lever(p - w, L)
    ha, hb, hc, hd = _lever(est - w, L)
    det = ha * hd - hb * hc
    det = np.where(np.abs(det) < 1e-12, np.nan, det)
    ia, ib, ic, id_ = hd / det, -hb / det, -hc / det, ha / det
    return a * ia + b * ic, a * ib + b * id_, c * ia + d * ic, c * ib + d * id_


def _smax_i_minus_k(m, k):
    """``||I - k M||_2`` of stacked 2 x 2 ``M`` (entries ``m``, each (n, i)) at gains ``k`` (n, 1)."""
    g00, g01, g10, g11 = 1 - k * m[0], -k * m[1], -k * m[2], 1 - k * m[3]
    f = g00 ** 2 + g01 ** 2 + g10 ** 2 + g11 ** 2
    dg = g00 * g11 - g01 * g10
    return np.sqrt((f + np.sqrt(np.maximum(f * f - 4 * dg * dg, 0))) / 2)


def rho_planar_peer(y, z, est, L, k, arm, chunk=16384, iters=40) -> tuple[np.ndarray, float]:
    """rho* at scale, numpy (issue 21): per tip the sampled motion maps of the 5 x 5 port box (the
    chunked elementwise peer's, reachability included), then a golden-section search over the gain
    in [0, 2 / max_i ||M_i||_F] of ``max_i ||I - k M_i||`` (convex in k), ``iters`` steps; the scenario
    gain is a candidate too, and no contraction (rho >= 1) gives 1. errplan's rho* is this sampled
    minimum certified by a refined worst case at k*, so it is never below it."""
    t0 = time.perf_counter()
    X = np.stack(np.meshgrid(y, z, indexing="ij"), -1).reshape(-1, 2)
    est = np.asarray(est, float)
    out = np.full(len(X), np.nan)
    gr = (np.sqrt(5.0) - 1) / 2
    old = np.seterr(divide="ignore", invalid="ignore")  # wrists of invalid instances: masked out below
    for c0 in range(0, len(X), chunk):
        Xc = X[c0:c0 + chunk]
        ok = np.ones(len(Xc), bool)
        ms = []
        for p, w, m in _peer_instances(Xc, est, L, arm):
            ok &= m
            ms.append(_peer_motion_map(p, est, w, L))
        v = ok & np.all(np.isfinite(np.array([mm[0] for mm in ms])), axis=0)
        if not v.any():
            continue
        M = [np.stack([mm[q][v] for mm in ms], axis=1) for q in range(4)]  # 4 x (n, 25)
        fro = np.sqrt(np.max(M[0] ** 2 + M[1] ** 2 + M[2] ** 2 + M[3] ** 2, axis=1))
        a, b = np.zeros(len(fro)), (2 / np.where(fro > 0, fro, 1.0))
        c, d = b - gr * (b - a), a + gr * (b - a)
        fc = _smax_i_minus_k(M, c[:, None]).max(axis=1)
        fd = _smax_i_minus_k(M, d[:, None]).max(axis=1)
        for _ in range(iters):
            left = fc < fd
            b = np.where(left, d, b)
            a = np.where(left, a, c)
            nc = np.where(left, b - gr * (b - a), d)
            nd = np.where(left, c, a + gr * (b - a))
            new = np.where(left, nc, nd)
            fn = _smax_i_minus_k(M, new[:, None]).max(axis=1)
            fd, fc = np.where(left, fc, fn), np.where(left, fn, fd)
            c, d = nc, nd
        kk = 0.5 * (a + b)
        rho = np.minimum(_smax_i_minus_k(M, kk[:, None]).max(axis=1), _smax_i_minus_k(M, np.full((len(kk), 1), k)).max(axis=1))
        out[c0 + np.flatnonzero(v)] = np.minimum(rho, 1.0)
    np.seterr(**old)
    return out.reshape(len(y), len(z)), time.perf_counter() - t0


def chunked_spatial_peer(axes, est, L, k, box, samples, chunk=8) -> tuple[np.ndarray, float]:
    """The elementwise spatial peer (:func:`numpy_spatial_elementwise`) over slabs of ``chunk``
    planes of the first axis (no reachability, as that peer)."""
    t0 = time.perf_counter()
    parts = [numpy_spatial_elementwise([axes[0][i:i + chunk], *axes[1:]], est, L, k, box, samples)[0]
             for i in range(0, len(axes[0]), chunk)]
    return np.concatenate(parts, axis=0), time.perf_counter() - t0


def machine_limit(n_tips: int = 200_000) -> dict[str, float]:
    """An estimate of this machine's limit: CPU ns per (tip x instance) of the bare arithmetic of one
    sampled instance (the lever wrist, ``M = J Jhat^-1``, the largest singular value of ``I - k M``) in a
    tight compiled loop on one core, no reachability, no search: planar (2 x 2, conformal parts) and
    spatial (3 x 3, cofactor inverse, trigonometric eigenvalue). A field's sampled pass cannot cost
    less per instance; its refinement and reachability come on top."""
    import numba

    @numba.njit(cache=False, fastmath=False)
    def planar(X, P, est, L, k):
        acc = 0.0
        for i in range(X.shape[0]):
            for j in range(P.shape[0]):
                e0, e1 = X[i, 0] - P[j, 0], X[i, 1] - P[j, 1]
                r = np.sqrt(e0 * e0 + e1 * e1)
                w0, w1 = X[i, 0] - L * e0 / r, X[i, 1] - L * e1 / r
                h = L / (2.0 * (L - r))
                n1r, n1i = -h * (e1 * e1 - e0 * e0) / (r * r), 2.0 * h * e0 * e1 / (r * r)
                dy, dz = est[0] - w0, est[1] - w1
                rho2 = dy * dy + dz * dz
                h2 = L / (2.0 * np.sqrt(rho2))
                m2 = 1.0 - h2
                n2r, n2i = -h2 * (dz * dz - dy * dy) / rho2, 2.0 * h2 * dz * dy / rho2
                det = m2 * m2 - n2r * n2r - n2i * n2i
                imr, inr, ini = m2 / det, -n2r / det, -n2i / det
                m1 = 1.0 - h
                mr = m1 * imr + n1r * inr + n1i * ini
                mi = n1i * inr - n1r * ini
                nr = m1 * inr + n1r * imr
                ni = m1 * ini + n1i * imr
                acc += np.sqrt((1 - k * mr) ** 2 + (k * mi) ** 2) + k * np.sqrt(nr * nr + ni * ni)
        return acc

    @numba.njit(cache=False, fastmath=False, inline="always")
    def lever3(d0, d1, d2, L):
        rho = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        sc, u0, u1, u2 = L / rho, d0 / rho, d1 / rho, d2 / rho
        return (1 - sc + sc * u0 * u0, sc * u0 * u1, sc * u0 * u2, sc * u1 * u0, 1 - sc + sc * u1 * u1, sc * u1 * u2,
                sc * u2 * u0, sc * u2 * u1, 1 - sc + sc * u2 * u2)

    @numba.njit(cache=False, fastmath=False)
    def spatial(X, P, est, L, k):
        acc = 0.0
        for i in range(X.shape[0]):
            for j in range(P.shape[0]):
                e0, e1, e2 = X[i, 0] - P[j, 0], X[i, 1] - P[j, 1], X[i, 2] - P[j, 2]
                r = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                w0, w1, w2 = X[i, 0] - L * e0 / r, X[i, 1] - L * e1 / r, X[i, 2] - L * e2 / r
                j00, j01, j02, j10, j11, j12, j20, j21, j22 = lever3(P[j, 0] - w0, P[j, 1] - w1, P[j, 2] - w2, L)
                h00, h01, h02, h10, h11, h12, h20, h21, h22 = lever3(est[0] - w0, est[1] - w1, est[2] - w2, L)
                c00, c01, c02 = h11 * h22 - h12 * h21, h12 * h20 - h10 * h22, h10 * h21 - h11 * h20
                idet = 1.0 / (h00 * c00 + h01 * c01 + h02 * c02)
                i00, i01, i02 = c00 * idet, (h02 * h21 - h01 * h22) * idet, (h01 * h12 - h02 * h11) * idet
                i10, i11, i12 = c01 * idet, (h00 * h22 - h02 * h20) * idet, (h02 * h10 - h00 * h12) * idet
                i20, i21, i22 = c02 * idet, (h01 * h20 - h00 * h21) * idet, (h00 * h11 - h01 * h10) * idet
                g00 = 1 - k * (j00 * i00 + j01 * i10 + j02 * i20)
                g01 = -k * (j00 * i01 + j01 * i11 + j02 * i21)
                g02 = -k * (j00 * i02 + j01 * i12 + j02 * i22)
                g10 = -k * (j10 * i00 + j11 * i10 + j12 * i20)
                g11 = 1 - k * (j10 * i01 + j11 * i11 + j12 * i21)
                g12 = -k * (j10 * i02 + j11 * i12 + j12 * i22)
                g20 = -k * (j20 * i00 + j21 * i10 + j22 * i20)
                g21 = -k * (j20 * i01 + j21 * i11 + j22 * i21)
                g22 = 1 - k * (j20 * i02 + j21 * i12 + j22 * i22)
                a00 = g00 * g00 + g10 * g10 + g20 * g20
                a11 = g01 * g01 + g11 * g11 + g21 * g21
                a22 = g02 * g02 + g12 * g12 + g22 * g22
                a01 = g00 * g01 + g10 * g11 + g20 * g21
                a02 = g00 * g02 + g10 * g12 + g20 * g22
                a12 = g01 * g02 + g11 * g12 + g21 * g22
                q = (a00 + a11 + a22) / 3
                pp = np.sqrt(((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6)
                ip = 1.0 / pp if pp > 0 else 1.0
                b00, b11, b22, b01, b02, b12 = (a00 - q) * ip, (a11 - q) * ip, (a22 - q) * ip, a01 * ip, a02 * ip, a12 * ip
                dB = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
                acc += np.sqrt(max(q + 2 * pp * np.cos(np.arccos(min(1.0, max(-1.0, dB / 2))) / 3), 0.0))
        return acc

    rng = np.random.default_rng(0)
    out = {}
    for name, f, d, m in (("planar", planar, 2, 25), ("spatial", spatial, 3, 27)):
        est = np.array([0.0, 0.0, 0.16])[-d:]
        P = est + rng.uniform(-0.005, 0.005, (m, d))
        X = est + np.concatenate([np.zeros((n_tips, d - 1)), np.full((n_tips, 1), 0.12)], 1) + rng.uniform(-0.08, 0.08, (n_tips, d))
        f(X[:2], P, est, 0.32, 1.0)
        c0 = time.process_time()
        f(X, P, est, 0.32, 1.0)
        out[name] = (time.process_time() - c0) / (n_tips * m) * 1e9
    return out


def at_scale(tmp: Path, repeat: int, rho_res: float = RHO_RES) -> list[str]:
    """Issue 21's two problems, errplan (whole process and in process) and its peer alternately in
    one run: planar 0.25 mm over P1's workspace with a 5 x 5 port box (the chunked planar peer,
    reachability included), spatial PHANToM 1.5 task region at 2 mm with 3 x 3 x 3 ports (the
    elementwise peer, chunked, no reachability). Per-instance costs are CPU time over
    (grid tips x sampled instances): errplan's includes its refinement and reachability."""
    from errplan.api import load_scenario
    from errplan.fields import MetricField, compute_fields
    from errplan.kinematics import arm_for

    lines = []
    sp, so = planar_scenario(tmp), spatial_scenario(tmp, 0.002, 3)
    scp, sco = load_scenario(sp), load_scenario(so)
    run_cli([str(sp), "--out", str(tmp / "warm.npz"), "--resolution", "0.004", "--metrics", "G_norm"])
    run_cli([str(so), "--out", str(tmp / "warm3.npz"), "--resolution", "0.01", "--metrics", "G_norm"])
    arm = arm_for(scp.robot)
    u = sco.uncertainty
    res = {}
    for name, scen, cli_args, peer in (
            ("planar", scp, [str(sp), "--resolution", "0.00025"],
             lambda mf: chunked_planar_peer(mf.y, mf.z, scp.port.estimate, scp.instrument.length,
                                            scp.controller.gain, arm)),
            ("spatial", sco, [str(so)],
             lambda mf: chunked_spatial_peer(mf.axes, sco.port.estimate, sco.instrument.length,
                                             sco.controller.gain, [u.port_x, u.port_y, u.port_z], 3)),
            ("planar rho*", scp, [str(sp), "--resolution", str(rho_res)],
             lambda mf: rho_planar_peer(mf.y, mf.z, scp.port.estimate, scp.instrument.length,
                                        scp.controller.gain, arm))):
        t_cli, cpu_cli, t_in, t_peer, cpu_peer = [], [], [], [], []
        metric = "rho_star" if name == "planar rho*" else "G_norm"
        res_in = {"planar": 0.00025, "planar rho*": rho_res}.get(name)
        for _ in range(repeat):
            c0 = os.times()
            t_cli.append(run_cli([*cli_args, "--out", str(tmp / f"{name}.npz"), "--metrics", metric]))
            c1 = os.times()
            cpu_cli.append(c1.children_user + c1.children_system - c0.children_user - c0.children_system)
            mf = MetricField.load(tmp / f"{name}.npz")
            t0 = time.perf_counter()
            compute_fields(scen, res_in, metrics=(metric,), workers=None)
            t_in.append(time.perf_counter() - t0)
            c0 = time.process_time()
            worst, tp = peer(mf)
            cpu_peer.append(time.process_time() - c0)
            t_peer.append(tp)
        mine = mf.rho_star if metric == "rho_star" else mf.G_norm
        both = mf.valid & np.isfinite(worst)
        diff = np.abs(worst[both] - mine[both])
        # G_norm: the peer's sampled worst case never above errplan's; rho*: errplan's certified rho* never
        # below the peer's sampled minimum (the peer's golden section stops within about 1e-8 of it)
        below = float(np.max((worst[both] - mine[both]) / np.maximum(1, worst[both])))
        same_valid = float(np.mean(mf.valid == np.isfinite(worst)))
        n, m = mf.valid.size, 27 if name == "spatial" else 25
        med = statistics.median
        res[name] = med(t_cli) / med(t_peer)
        label = {"planar": "planar 0.25 mm, 5 x 5", "spatial": "spatial 2 mm, 3 x 3 x 3",
                 "planar rho*": f"planar rho* {rho_res * 1000:g} mm, 5 x 5"}[name]
        lines.append(f"| {label} | {n:,} ({int(mf.valid.sum()):,} valid) | {med(t_cli):.2f} ({med(cpu_cli):.1f} CPU) | "
                     f"{med(t_in):.2f} | {med(t_peer):.2f} | {res[name]:.2f} | "
                     f"{med(cpu_cli) / (n * m) * 1e9:.0f} | {med(cpu_peer) / (n * m) * 1e9:.0f} | "
                     f"{np.mean(diff <= 1e-3) * 100:.2f} % / {below:.1e} / {same_valid * 100:.2f} % |")
    lim = machine_limit()
    lines.append("")
    lines.append(f"machine limit (bare arithmetic of one sampled instance, compiled, one core, CPU ns per tip x instance): "
                 f"planar {lim['planar']:.0f}, spatial {lim['spatial']:.0f}; at that cost on both cores the sampled pass alone "
                 f"would take planar 0.25 mm {lim['planar'] * 3_104_200 * 25 / 2e9:.2f} s, spatial 2 mm "
                 f"{lim['spatial'] * 1_185_921 * 27 / 2e9:.2f} s of wall time")
    head = ["| problem | grid tips | errplan whole process, s (CPU s) | errplan in process, s | peer in process, s | "
            "ratio whole/peer | errplan CPU ns per tip x instance | peer CPU ns per tip x instance | "
            "agree within 1e-3 / peer above errplan by at most / same validity |", "|---|---|---|---|---|---|---|---|---|"]
    return head + lines, res


def _cli_cpu(args: list[str]) -> float:
    """CPU seconds (user + system, the command and its worker processes) of one ``errplan fields`` run."""
    c0 = os.times()
    run_cli(args)
    c1 = os.times()
    return c1.children_user + c1.children_system - c0.children_user - c0.children_system


def where_time(tmp: Path, repeat: int) -> list[str]:
    """Where the CPU time of the two problems at scale goes (planar 0.25 mm, 5 x 5 port box; spatial 2 mm,
    3 x 3 x 3 ports; ``G_norm``): the whole ``errplan fields`` process (both cores, its workers included);
    its start-up, the same command on a coarse grid (interpreter, imports, kernel cache load, scenario,
    arm and reachability map, npz written); and in this process on one worker the entry search (per tip:
    reachability certificate, the sampled instances, the choice of the starts), the straight-shaft
    refinements run as lanes (:func:`errplan.fields.kernels.run_lanes`) and the Python around them (grid,
    prefilter, tiles, scatter). Medians of ``repeat``; CPU ns per (grid tip x sampled instance)."""
    from errplan.api import load_scenario
    from errplan.fields import compute_fields
    from errplan.fields.kernels import loops

    sp, so = planar_scenario(tmp), spatial_scenario(tmp, 0.002, 3)
    acc = {"search": 0.0, "lanes": 0.0, "tips": 0, "lanes_n": 0}
    tiles, lanes0 = dict(loops._TILES), loops.run_lanes

    def timed(f):
        def g(X, *a):
            c0 = time.process_time()
            f(X, *a)
            acc["search"] += time.process_time() - c0
            acc["tips"] += len(X)
        return g

    def run_lanes(lanes, *a):
        c0 = time.process_time()
        lanes0(lanes, *a)
        acc["lanes"] += time.process_time() - c0
        acc["lanes_n"] += int(lanes.count[0])

    lines = ["| problem | grid tips (candidates, valid) | whole process CPU s | start-up CPU s | in process, 1 worker: "
             "CPU s | search (sampled pass, starts) s | refinement lanes s (lanes) | Python s | ns per tip x instance: "
             "whole / in process / search / lanes |", "|---|---|---|---|---|---|---|---|---|"]
    for name, path, res, coarse, m in (("planar 0.25 mm, 5 x 5", sp, 0.00025, 0.004, 25),
                                       ("spatial 2 mm, 3 x 3 x 3", so, None, 0.02, 27)):
        sc = load_scenario(path)
        base = [str(path), "--metrics", "G_norm", "--out", str(tmp / "where.npz")]
        fine = base + (["--resolution", str(res)] if res else [])
        _cli_cpu(base + ["--resolution", str(coarse)])  # the kernel cache warm
        whole = statistics.median(_cli_cpu(fine) for _ in range(repeat))
        start = statistics.median(_cli_cpu(base + ["--resolution", str(coarse)]) for _ in range(repeat))
        compute_fields(sc, coarse, metrics=("G_norm",), workers=1)
        rows = []
        try:
            loops._TILES.update({k: timed(f) for k, f in tiles.items()})
            loops.run_lanes = run_lanes
            for _ in range(repeat):
                acc.update(search=0.0, lanes=0.0, tips=0, lanes_n=0)
                c0 = time.process_time()
                mf = compute_fields(sc, res, metrics=("G_norm",), workers=1)
                rows.append((time.process_time() - c0, acc["search"], acc["lanes"]))
        finally:
            loops._TILES.update(tiles)
            loops.run_lanes = lanes0
        tot, srch, lan = (statistics.median(r[i] for r in rows) for i in range(3))
        n = mf.valid.size
        per = lambda t: t / (n * m) * 1e9  # noqa: E731
        lines.append(f"| {name} | {n:,} ({acc['tips']:,}, {int(mf.valid.sum()):,}) | {whole:.2f} | {start:.2f} | "
                     f"{tot:.2f} | {srch:.2f} | {lan:.2f} ({acc['lanes_n']:,}) | {tot - srch - lan:.2f} | "
                     f"{per(whole):.0f} / {per(tot):.0f} / {per(srch):.0f} / {per(lan):.0f} |")
    return lines


def peer_rows(kind, what, times, stacked, t_stacked, target, elementwise, t_elem) -> list[tuple[str, float]]:
    """Rows of errplan's median time against the two numpy peers' and the ratios."""
    t, ts, te = statistics.median(times), statistics.median(t_stacked), statistics.median(t_elem)
    return [(f"{kind}: {what}", t), (f"{kind}: {stacked}", ts), (f"{kind} ratio to it (target <= {target:g})", t / ts),
            (f"{kind}: {elementwise}", te), (f"{kind} ratio to it", t / te)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="fewer scaling points")
    ap.add_argument("--rho-res", type=float, default=RHO_RES, help="--scale: the rho* row's planar grid spacing, m")
    ap.add_argument("--scale", action="store_true",
                    help="only issue 21's problems at scale (planar 0.25 mm, spatial 2 mm) and their targets")
    ap.add_argument("--where", action="store_true",
                    help="only where the CPU time of the problems at scale goes (start-up, search, lanes, Python)")
    a = ap.parse_args()
    if a.where:
        load0 = os.getloadavg()[0]
        with tempfile.TemporaryDirectory() as d:
            lines = where_time(Path(d), a.repeat)
        print(f"{os.cpu_count()} cores, load average (1 min) {load0:.2f} before, {os.getloadavg()[0]:.2f} after the run; "
              f"medians of {a.repeat}; CPU seconds")
        print()
        print("\n".join(lines))
        return 0
    if a.scale:
        load0 = os.getloadavg()[0]
        with tempfile.TemporaryDirectory() as d:
            lines, res = at_scale(Path(d), a.repeat, a.rho_res)
        print(f"{os.cpu_count()} cores, load average (1 min) {load0:.2f} before, {os.getloadavg()[0]:.2f} after the run; medians of "
              f"{a.repeat}, errplan and peer alternately")
        print()
        print("\n".join(lines))
        ok = res["planar"] <= PLANAR_TARGET and res["spatial"] <= SPATIAL_TARGET
        print()
        print(f"targets (planar <= {PLANAR_TARGET}, spatial <= {SPATIAL_TARGET}): planar {res['planar']:.2f} "
              f"{'met' if res['planar'] <= PLANAR_TARGET else 'NOT met'}, spatial {res['spatial']:.2f} "
              f"{'met' if res['spatial'] <= SPATIAL_TARGET else 'NOT met'}; rho* (no target set) {res['planar rho*']:.2f}")
        return 0 if ok else 1
    from errplan.fields import MetricField, compute_fields
    from errplan.api import load_scenario

    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        # ---------------------------------------------------------------- planar
        sp = planar_scenario(tmp)
        sc = load_scenario(sp)
        run_cli([str(sp), "--out", str(tmp / "warm.npz"), "--resolution", "0.004"])  # fill the kernel cache
        t_a = [run_cli([str(sp), "--out", str(tmp / "p.npz"), "--resolution", "0.001"]) for _ in range(a.repeat)]
        mf = MetricField.load(tmp / "p.npz")
        runs = [numpy_planar(mf.y, mf.z, sc.port.estimate, sc.instrument.length, sc.controller.gain)
                for _ in range(a.repeat)]
        worst = runs[0][0]
        t_b = [r[1] for r in runs]
        t_b2 = [numpy_planar_stacked(mf.y, mf.z, sc.port.estimate, sc.instrument.length, sc.controller.gain)[1]
                for _ in range(a.repeat)]
        both = mf.valid & np.isfinite(worst)
        below_p = float(np.max((worst[both] - mf.G_norm[both]) / np.maximum(1, worst[both])))
        rows += peer_rows("planar", "`errplan fields` process, 1 mm grid, 5 x 5 port box", t_a,
                          "plain numpy, stacked inv/matmul, closed-form sigma_max (issue 2's baseline)", t_b2, 0.5,
                          "plain numpy written out elementwise, closed-form sigma_max (the strongest peer)", t_b)
        n_planar = (len(mf.y) * len(mf.z), int(mf.valid.sum()))
        # ---------------------------------------------------------------- spatial
        so = spatial_scenario(tmp)
        sco = load_scenario(so)
        run_cli([str(so), "--out", str(tmp / "warm3.npz"), "--metrics", "G_norm", "--resolution", "0.01"])
        t_c = [run_cli([str(so), "--out", str(tmp / "o.npz"), "--metrics", "G_norm"]) for _ in range(a.repeat)]
        mo = MetricField.load(tmp / "o.npz")
        u = sco.uncertainty
        runs = [numpy_spatial(mo.axes, sco.port.estimate, sco.instrument.length, sco.controller.gain,
                              [u.port_x, u.port_y, u.port_z], 3) for _ in range(a.repeat)]
        worst3 = runs[0][0]
        t_d = [r[1] for r in runs]
        runs_e = [numpy_spatial_elementwise(mo.axes, sco.port.estimate, sco.instrument.length, sco.controller.gain,
                                            [u.port_x, u.port_y, u.port_z], 3) for _ in range(a.repeat)]
        t_d2 = [r[1] for r in runs_e]
        fin = np.isfinite(worst3)
        agree = float(np.max(np.abs(runs_e[0][0][fin] - worst3[fin]) / np.maximum(1, worst3[fin])))
        both = mo.valid & np.isfinite(worst3)
        below_s = float(np.max((worst3[both] - mo.G_norm[both]) / np.maximum(1, worst3[both])))
        rows += peer_rows("spatial", "`errplan fields --metrics G_norm` process, PHANToM 1.5, 4 mm region, 3 x 3 x 3",
                          t_c, "plain numpy worst sigma_max, stacked 3 x 3 (inv, matmul; no refinement/reach)", t_d,
                          0.25, "plain numpy written out elementwise (the strongest peer)", t_d2)
        n_spatial = (mo.valid.size, int(mo.valid.sum()))
        # ---------------------------------------------------------------- compile cost
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / "cold-cache"))
        t_cold = run_cli([str(so), "--out", str(tmp / "c.npz"), "--metrics", "G_norm", "--resolution", "0.01"], env)
        t_warm = run_cli([str(so), "--out", str(tmp / "c.npz"), "--metrics", "G_norm", "--resolution", "0.01"], env)
        rows.append(("first run, empty kernel cache (compile), PHANToM 1.5 10 mm", t_cold))
        rows.append(("second run, same cache, PHANToM 1.5 10 mm", t_warm))
        # ---------------------------------------------------------------- scaling
        scale = []
        resolutions = (0.008, 0.006, 0.004) if not a.quick else (0.008, 0.004)
        for res in resolutions:
            s = load_scenario(spatial_scenario(tmp, res))
            t0 = time.perf_counter()
            m = compute_fields(s, metrics=("G_norm",), workers=1)
            scale.append(("grid", f"{res * 1000:g} mm", m.valid.size, int(m.valid.sum()), 27, time.perf_counter() - t0))
        for n in ((2, 3, 4, 5) if not a.quick else (2, 4)):
            s = load_scenario(spatial_scenario(tmp, 0.006, n))
            t0 = time.perf_counter()
            m = compute_fields(s, metrics=("G_norm",), workers=1)
            scale.append(("instances", f"{n} per axis", m.valid.size, int(m.valid.sum()), n ** 3,
                          time.perf_counter() - t0))
        s = load_scenario(so)
        wt = {}
        for w in (1, 2):
            t0 = time.perf_counter()
            compute_fields(s, metrics=("G_norm",), workers=w)
            wt[w] = time.perf_counter() - t0
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; medians of {a.repeat}; planar grid "
          f"{n_planar[0]} tips ({n_planar[1]} in the workspace), spatial grid {n_spatial[0]} tips "
          f"({n_spatial[1]} robustly valid)")
    print()
    print("| what | wall time (s) |")
    print("|---|---|")
    for name, v in rows:
        print(f"| {name} | {v:.2f} |")
    print()
    print("| scaling (spatial, PHANToM 1.5, in-process, 1 worker) | setting | grid points | valid | instances sampled | time (s) |")
    print("|---|---|---|---|---|---|")
    for kind, setting, n, nv, m, t in scale:
        print(f"| {kind} | {setting} | {n} | {nv} | {m} | {t:.2f} |")
    print()
    print(f"workers (PHANToM 1.5 4 mm, G_norm, in-process): 1 worker {wt[1]:.2f} s, 2 workers {wt[2]:.2f} s, "
          f"speed-up {wt[1] / wt[2]:.2f}")
    print(f"errplan never below numpy's sampled worst case: planar by at most {below_p:.1e}, spatial {below_s:.1e} "
          "(relative; errplan's refinement only adds)")
    print(f"the two spatial numpy peers agree to {agree:.1e} (relative)")
    ratios = dict(rows)
    ok = (ratios["planar ratio to it (target <= 0.5)"] <= 0.5
          and ratios["spatial ratio to it (target <= 0.25)"] <= 0.25)
    print("targets met" if ok else "targets not met")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
