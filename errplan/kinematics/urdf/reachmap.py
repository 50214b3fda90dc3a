"""The reachability map of a URDF arm's wrist workspace (the package docstring states its guarantees):
the compiled build (face patches and joint cells bounded by image balls; one flood fill, :func:`_flood`,
that labels the out and in voxels and hands IK seeds on to the seed cells without), the bounds it rests
on, and its on-disk cache."""
from __future__ import annotations

import math
import contextlib
import hashlib
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from ...jit import njit

from .chain import _box, _dot, _fkjac3, _fkjacz3, _rows_ok
from .model import MAP_VERSION, TWO_PI, ReachMap, cache_dir


@njit(cache=True, inline="always")
def _smin3(c0, c1, c2):
    """Smallest singular value of the 3x3 matrix with columns c0, c1, c2."""
    a00, a01, a02 = _dot(c0, c0), _dot(c0, c1), _dot(c0, c2)
    a11, a12, a22 = _dot(c1, c1), _dot(c1, c2), _dot(c2, c2)
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    if p1 == 0.0:
        lmin = min(a00, min(a11, a22))
    else:
        p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
        p = math.sqrt(p2 / 6.0)
        b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
        b01, b02, b12 = a01 / p, a02 / p, a12 / p
        detb = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
        r = min(1.0, max(-1.0, detb / 2.0))
        phi = math.acos(r) / 3.0
        lmin = q + 2.0 * p * math.cos(phi + TWO_PI / 3.0)
    return math.sqrt(max(lmin, 0.0))


@njit(cache=True, inline="always")
def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True, inline="always")
def _det(a, b, c):
    return _dot(a, _cross(b, c))


@njit(cache=True, inline="always")
def _djac(jt, j, k, zj, zk, Jj, Jk):
    """d J_j / d q_k of a serial chain (jt: joint types)."""
    if jt[j] == 0:
        if k < j:
            if jt[k] == 0:
                return _cross(zk, Jj)
            return (0.0, 0.0, 0.0)
        return _cross(zj, Jk)
    if k < j and jt[k] == 0:
        return _cross(zk, zj)
    return (0.0, 0.0, 0.0)


@njit(cache=True)
def _nonsingular(chain, c0, c1, c2, z0, z1, z2, e0, e1, e2, M2):
    """True if det J cannot vanish on the cell (second-order Taylor bound, M2 bounds d2 det)."""
    jt = chain.jtype
    d = _det(c0, c1, c2)
    g = 0.0
    for k in range(3):
        zk = z0 if k == 0 else (z1 if k == 1 else z2)
        Jk = c0 if k == 0 else (c1 if k == 1 else c2)
        ek = e0 if k == 0 else (e1 if k == 1 else e2)
        g += abs(_det(_djac(jt, 0, k, z0, zk, c0, Jk), c1, c2)
                 + _det(c0, _djac(jt, 1, k, z1, zk, c1, Jk), c2)
                 + _det(c0, c1, _djac(jt, 2, k, z2, zk, c2, Jk))) * ek
    quad = 0.5 * (M2[0, 0] * e0 * e0 + M2[1, 1] * e1 * e1 + M2[2, 2] * e2 * e2
                  + 2.0 * (M2[0, 1] * e0 * e1 + M2[0, 2] * e0 * e2 + M2[1, 2] * e1 * e2))
    return abs(d) > (g + quad) * (1.0 + 1e-9) + 1e-18


@njit(cache=True)
def _cell_feasible(chain, c0, c1, c2, e0, e1, e2):
    """Can the cell (centre c, half-widths e) meet Q? False only if a limit row fails on all of it."""
    A = chain.A
    for r in range(A.shape[0]):
        m = A[r, 0] * c0 + A[r, 1] * c1 + A[r, 2] * c2
        s = abs(A[r, 0]) * e0 + abs(A[r, 1]) * e1 + abs(A[r, 2]) * e2
        lo = chain.lo[r]
        hi = chain.hi[r]
        slack = 1e-9 * (1.0 + abs(lo) + abs(hi) + s)
        if m + s < lo - slack or m - s > hi + slack:
            return False
    return True


@njit(cache=True)
def _coarse_bbox(chain, K, jlo, djoint, ncell):
    """Bounding box of the image balls of all feasible coarse cells, and the largest ball."""
    bmin = np.full(3, np.inf)
    bmax = np.full(3, -np.inf)
    e0, e1, e2 = 0.5 * djoint[0], 0.5 * djoint[1], 0.5 * djoint[2]
    q2term = 0.5 * K * (e0 * e0 + e1 * e1 + e2 * e2)
    rmax = 0.0
    for i in range(ncell[0]):
        c0 = jlo[0] + (i + 0.5) * djoint[0]
        for j in range(ncell[1]):
            c1 = jlo[1] + (j + 0.5) * djoint[1]
            for k in range(ncell[2]):
                c2 = jlo[2] + (k + 0.5) * djoint[2]
                if not _cell_feasible(chain, c0, c1, c2, e0, e1, e2):
                    continue
                w, a, b, c = _fkjac3(chain, c0, c1, c2)
                rho = (math.sqrt(_dot(a, a)) * e0 + math.sqrt(_dot(b, b)) * e1
                       + math.sqrt(_dot(c, c)) * e2 + q2term) * (1.0 + 1e-9) + 1e-12
                rmax = max(rmax, rho)
                for d in range(3):
                    bmin[d] = min(bmin[d], w[d] - rho)
                    bmax[d] = max(bmax[d], w[d] + rho)
    return bmin, bmax, rmax


@njit(cache=True)
def _add_seed(sd, sdist, scnt, v, q0, q1, q2, dist, tau):
    S = sd.shape[1]
    n = scnt[v]
    for k in range(n):
        if (abs(sd[v, k, 0] - q0) < tau and abs(sd[v, k, 1] - q1) < tau
                and abs(sd[v, k, 2] - q2) < tau):
            if dist < sdist[v, k]:
                sd[v, k, 0], sd[v, k, 1], sd[v, k, 2] = q0, q1, q2
                sdist[v, k] = dist
            return
    if n < S:
        sd[v, n, 0], sd[v, n, 1], sd[v, n, 2] = q0, q1, q2
        sdist[v, n] = dist
        scnt[v] = n + 1
        return
    worst = 0
    for k in range(1, S):
        if sdist[v, k] > sdist[v, worst]:
            worst = k
    if dist < sdist[v, worst]:
        sd[v, worst, 0], sd[v, worst, 1], sd[v, worst, 2] = q0, q1, q2
        sdist[v, worst] = dist


@njit(cache=True, inline="always")
def _neighbour6(ix, iy, iz, d):
    if d == 0:
        return ix - 1, iy, iz
    if d == 1:
        return ix + 1, iy, iz
    if d == 2:
        return ix, iy - 1, iz
    if d == 3:
        return ix, iy + 1, iz
    if d == 4:
        return ix, iy, iz - 1
    return ix, iy, iz + 1


@njit(cache=True, inline="always")
def _step6(v, nx, ny, nz, d):
    """Linear index of the ``d``-th face neighbour (0..5) of cell ``v`` of an (nx, ny, nz) grid, or -1 off
    the grid: the neighbourhood of :func:`_flood`."""
    jx, jy, jz = _neighbour6(v // (ny * nz), (v // nz) % ny, v % nz, d)
    if jx < 0 or jy < 0 or jz < 0 or jx >= nx or jy >= ny or jz >= nz:
        return -1
    return (jx * ny + jy) * nz + jz


@njit(cache=True)
def _flood(free, queue, qt, nx, ny, nz, parent):
    """The one flood fill of the map (voxel labels, seed cells): breadth first over the face neighbours
    of an (nx, ny, nz) grid, from the sources ``queue[:qt]`` into every ``free`` cell connected to them
    through free cells. Each cell entered is no longer free, joins the queue and, if ``parent`` has
    room, records the cell it was entered from. Returns the queue's length: ``queue[:qt]`` the sources,
    then the cells entered, in order (a cell after the one it was entered from)."""
    qh = 0
    while qh < qt:
        v = queue[qh]
        qh += 1
        for d in range(6):
            u = _step6(v, nx, ny, nz, d)
            if u < 0 or not free[u]:
                continue
            free[u] = False
            if parent.size > 0:
                parent[u] = v
            queue[qt] = u
            qt += 1
    return qt


@njit(cache=True, inline="always")
def _grid_coords(w, origin, h, nx, ny, nz):
    """A point's coordinates in voxel units, and whether it lies in the (nx, ny, nz) grid."""
    fx = (w[0] - origin[0]) / h
    fy = (w[1] - origin[1]) / h
    fz = (w[2] - origin[2]) / h
    return fx, fy, fz, (fx >= 0.0 and fx < nx and fy >= 0.0 and fy < ny and fz >= 0.0 and fz < nz)


@njit(cache=True)
def _mark_ball(bnd, w, rho, origin, h, nx, ny, nz):
    """Flag every voxel that meets the ball B(w, rho)."""
    lo0 = max(0, int(math.floor((w[0] - rho - origin[0]) / h)))
    hi0 = min(nx - 1, int(math.floor((w[0] + rho - origin[0]) / h)))
    lo1 = max(0, int(math.floor((w[1] - rho - origin[1]) / h)))
    hi1 = min(ny - 1, int(math.floor((w[1] + rho - origin[1]) / h)))
    lo2 = max(0, int(math.floor((w[2] - rho - origin[2]) / h)))
    hi2 = min(nz - 1, int(math.floor((w[2] + rho - origin[2]) / h)))
    r2 = rho * rho
    for ix in range(lo0, hi0 + 1):
        x0 = origin[0] + ix * h
        dx = max(0.0, max(x0 - w[0], w[0] - x0 - h))
        for iy in range(lo1, hi1 + 1):
            y0 = origin[1] + iy * h
            dy = max(0.0, max(y0 - w[1], w[1] - y0 - h))
            for iz in range(lo2, hi2 + 1):
                z0 = origin[2] + iz * h
                dz = max(0.0, max(z0 - w[2], w[2] - z0 - h))
                if dx * dx + dy * dy + dz * dz <= r2:
                    bnd[(ix * ny + iy) * nz + iz] = 1


@njit(cache=True)
def _seed_at(chain, sd, sdist, scnt, fx, fy, fz, sub, cy, cz, c0, c1, c2, tau):
    """Offer configuration c (projected into the box) as a seed of the cell holding voxel coords f."""
    jx, jy, jz = int(fx) // sub, int(fy) // sub, int(fz) // sub
    ux = fx / sub - jx - 0.5
    uy = fy / sub - jy - 0.5
    uz = fz / sub - jz - 0.5
    _add_seed(sd, sdist, scnt, (jx * cy + jy) * cz + jz, _box(chain, 0, c0), _box(chain, 1, c1),
              _box(chain, 2, c2), ux * ux + uy * uy + uz * uz, tau)


@njit(cache=True)
def _build_map(chain, K, M2, jlo, djoint, ncell, faces, origin, h, shape, sub, beta, max_depth, S, tau):
    """Classify the voxels and collect IK seeds (see the module docstring).

    Returns state (nx, ny, nz) uint8, seed_ptr, seeds, stats (int64: leaves, critical leaves,
    conflicts, seed cells without seeds).
    """
    nx, ny, nz = shape[0], shape[1], shape[2]
    nvox = nx * ny * nz
    cx, cy, cz = nx // sub, ny // sub, nz // sub
    ncel = cx * cy * cz
    bnd = np.zeros(nvox, np.uint8)
    hit = np.zeros(nvox, np.uint8)
    sd = np.zeros((ncel, S, 3), np.float64)
    sdist = np.full((ncel, S), np.inf, np.float32)
    scnt = np.zeros(ncel, np.int64)
    cap = 8 * (max_depth + 2)
    st = np.empty((cap, 6))
    sdep = np.empty(cap, np.int64)
    n_leaf = 0
    n_crit = 0
    for i in range(ncell[0]):
        for j in range(ncell[1]):
            for k in range(ncell[2]):
                st[0, 0] = jlo[0] + (i + 0.5) * djoint[0]
                st[0, 1] = jlo[1] + (j + 0.5) * djoint[1]
                st[0, 2] = jlo[2] + (k + 0.5) * djoint[2]
                st[0, 3] = 0.5 * djoint[0]
                st[0, 4] = 0.5 * djoint[1]
                st[0, 5] = 0.5 * djoint[2]
                sdep[0] = 0
                top = 1
                while top > 0:
                    top -= 1
                    c0, c1, c2 = st[top, 0], st[top, 1], st[top, 2]
                    e0, e1, e2 = st[top, 3], st[top, 4], st[top, 5]
                    dep = sdep[top]
                    if not _cell_feasible(chain, c0, c1, c2, e0, e1, e2):
                        continue
                    w, a, b, c, z0, z1, z2 = _fkjacz3(chain, c0, c1, c2)
                    ee = e0 * e0 + e1 * e1 + e2 * e2
                    rho = (math.sqrt(_dot(a, a)) * e0 + math.sqrt(_dot(b, b)) * e1
                           + math.sqrt(_dot(c, c)) * e2 + 0.5 * K * ee) * (1.0 + 1e-9) + 1e-12
                    # may the cell hold a singular configuration? (Weyl on sigma_min, then det J)
                    crit = False
                    if _smin3(a, b, c) <= K * math.sqrt(ee) * (1.0 + 1e-9) + 1e-9:
                        crit = not _nonsingular(chain, a, b, c, z0, z1, z2, e0, e1, e2, M2)
                    if crit and rho > beta * h and dep < max_depth:
                        for s0 in (-0.5, 0.5):
                            for s1 in (-0.5, 0.5):
                                for s2 in (-0.5, 0.5):
                                    st[top, 0] = c0 + s0 * e0
                                    st[top, 1] = c1 + s1 * e1
                                    st[top, 2] = c2 + s2 * e2
                                    st[top, 3] = 0.5 * e0
                                    st[top, 4] = 0.5 * e1
                                    st[top, 5] = 0.5 * e2
                                    sdep[top] = dep + 1
                                    top += 1
                        continue
                    n_leaf += 1
                    if crit:
                        n_crit += 1
                        _mark_ball(bnd, w, rho, origin, h, nx, ny, nz)
                    fx, fy, fz, inside = _grid_coords(w, origin, h, nx, ny, nz)
                    if inside:
                        if _rows_ok(chain, c0, c1, c2, 0.0):
                            hit[(int(fx) * ny + int(fy)) * nz + int(fz)] = 1
                        _seed_at(chain, sd, sdist, scnt, fx, fy, fz, sub, cy, cz, c0, c1, c2, tau)
    # ---- the faces of Q (box faces of joints that do not wrap, coupled-limit planes), as
    # patches q = c + u t1 + v t2 refined (2-D) until their image ball has radius <= beta h
    n_face = 0
    pst = np.empty((4 * max_depth + 8, 5))
    A = chain.A
    for f in range(faces.shape[0]):
        pst[0, 0] = 0.5 * (faces[f, 9] + faces[f, 10])
        pst[0, 1] = 0.5 * (faces[f, 11] + faces[f, 12])
        pst[0, 2] = 0.5 * (faces[f, 10] - faces[f, 9])
        pst[0, 3] = 0.5 * (faces[f, 12] - faces[f, 11])
        pst[0, 4] = 0
        top = 1
        while top > 0:
            top -= 1
            u, v, eu, ev, dep = pst[top, 0], pst[top, 1], pst[top, 2], pst[top, 3], pst[top, 4]
            c0 = faces[f, 0] + u * faces[f, 3] + v * faces[f, 6]
            c1 = faces[f, 1] + u * faces[f, 4] + v * faces[f, 7]
            c2 = faces[f, 2] + u * faces[f, 5] + v * faces[f, 8]
            t1 = (faces[f, 3], faces[f, 4], faces[f, 5])
            t2 = (faces[f, 6], faces[f, 7], faces[f, 8])
            feas = True
            for r in range(A.shape[0]):
                m = A[r, 0] * c0 + A[r, 1] * c1 + A[r, 2] * c2
                sr = abs(A[r, 0] * t1[0] + A[r, 1] * t1[1] + A[r, 2] * t1[2]) * eu \
                    + abs(A[r, 0] * t2[0] + A[r, 1] * t2[1] + A[r, 2] * t2[2]) * ev
                slack = 1e-9 * (1.0 + abs(chain.lo[r]) + abs(chain.hi[r]) + sr)
                if m + sr < chain.lo[r] - slack or m - sr > chain.hi[r] + slack:
                    feas = False
                    break
            if not feas:
                continue
            w, a, b, c = _fkjac3(chain, c0, c1, c2)
            j1 = (a[0] * t1[0] + b[0] * t1[1] + c[0] * t1[2], a[1] * t1[0] + b[1] * t1[1] + c[1] * t1[2],
                  a[2] * t1[0] + b[2] * t1[1] + c[2] * t1[2])
            j2 = (a[0] * t2[0] + b[0] * t2[1] + c[0] * t2[2], a[1] * t2[0] + b[1] * t2[1] + c[1] * t2[2],
                  a[2] * t2[0] + b[2] * t2[1] + c[2] * t2[2])
            s1 = math.sqrt(_dot(j1, j1)) * eu
            s2 = math.sqrt(_dot(j2, j2)) * ev
            dq = math.sqrt(_dot(t1, t1)) * eu + math.sqrt(_dot(t2, t2)) * ev
            rho = (s1 + s2 + 0.5 * K * dq * dq) * (1.0 + 1e-9) + 1e-12
            if rho > beta * h and dep < 2 * max_depth:
                # halve the side that contributes more to rho (linear and quadratic terms)
                if s1 + 0.5 * K * dq * math.sqrt(_dot(t1, t1)) * eu >= s2 + 0.5 * K * dq * math.sqrt(_dot(t2, t2)) * ev:
                    for sg in (-0.5, 0.5):
                        pst[top, 0], pst[top, 1] = u + sg * eu, v
                        pst[top, 2], pst[top, 3], pst[top, 4] = 0.5 * eu, ev, dep + 1
                        top += 1
                else:
                    for sg in (-0.5, 0.5):
                        pst[top, 0], pst[top, 1] = u, v + sg * ev
                        pst[top, 2], pst[top, 3], pst[top, 4] = eu, 0.5 * ev, dep + 1
                        top += 1
                continue
            n_face += 1
            _mark_ball(bnd, w, rho, origin, h, nx, ny, nz)
            fx, fy, fz, inside = _grid_coords(w, origin, h, nx, ny, nz)
            if inside:
                _seed_at(chain, sd, sdist, scnt, fx, fy, fz, sub, cy, cz, c0, c1, c2, tau)
    # ---- flood fill of the non-boundary voxels: out from the border layer, in from the hits
    lab = np.zeros(nvox, np.uint8)   # 0 unknown, 1 out, 2 in
    queue = np.empty(nvox, np.int64)
    no_parent = np.empty(0, np.int64)
    conflicts = 0
    for pas in range(2):
        free = (bnd == 0) & (lab == 0)
        qt = 0
        for v in range(nvox):
            if not free[v]:
                continue
            iz = v % nz
            iy = (v // nz) % ny
            ix = v // (ny * nz)
            if pas == 0:
                start = ix == 0 or iy == 0 or iz == 0 or ix == nx - 1 or iy == ny - 1 or iz == nz - 1
            else:
                start = hit[v] == 1
            if start:
                free[v] = False
                queue[qt] = v
                qt += 1
        qt = _flood(free, queue, qt, nx, ny, nz, no_parent)
        for k in range(qt):
            v = queue[k]
            lab[v] = 1 + pas
            if pas == 0 and hit[v]:
                conflicts += 1
    state = np.empty(nvox, np.uint8)
    cflag = np.zeros(ncel, np.uint8)   # 0 only out voxels, 1 some in, 2 some boundary
    for v in range(nvox):
        if bnd[v]:
            s = 2
        elif lab[v] == 1:
            s = 0
        elif lab[v] == 2:
            s = 1
        else:
            s = 2
        state[v] = s
        iz = v % nz
        iy = (v // nz) % ny
        ix = v // (ny * nz)
        c = ((ix // sub) * cy + iy // sub) * cz + iz // sub
        if s > cflag[c]:
            cflag[c] = s
    # ---- seeds: cells with boundary voxels take their own and their 26 neighbours' (one per
    # branch), cells with in voxels their own, else their neighbours'; any still without seeds
    # get the nearest cell's.
    S2 = S + 2
    fd = np.zeros((ncel, S2, 3), np.float64)
    fdist = np.full((ncel, S2), np.inf, np.float32)
    fcnt = np.zeros(ncel, np.int64)
    for c in range(ncel):
        if cflag[c] == 0:
            continue
        for k in range(scnt[c]):
            _add_seed(fd, fdist, fcnt, c, sd[c, k, 0], sd[c, k, 1], sd[c, k, 2], np.float64(sdist[c, k]), tau)
        if cflag[c] == 1 and fcnt[c] > 0:
            continue
        kz = c % cz
        ky = (c // cz) % cy
        kx = c // (cy * cz)
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    jx, jy, jz = kx + dx, ky + dy, kz + dz
                    if jx < 0 or jy < 0 or jz < 0 or jx >= cx or jy >= cy or jz >= cz:
                        continue
                    u = (jx * cy + jy) * cz + jz
                    if u == c:
                        continue
                    off = float(dx * dx + dy * dy + dz * dz)
                    for k in range(scnt[u]):
                        _add_seed(fd, fdist, fcnt, c, sd[u, k, 0], sd[u, k, 1], sd[u, k, 2],
                                  sdist[u, k] + off, tau)
    # cells with seeds hand them on (one more cell away each step) to the cells still without
    free = (cflag != 0) & (fcnt == 0)
    cq = np.empty(ncel, np.int64)
    parent = np.empty(ncel, np.int64)
    qt = 0
    for c in range(ncel):
        if cflag[c] != 0 and fcnt[c] > 0:
            cq[qt] = c
            qt += 1
    q0 = qt
    qt = _flood(free, cq, qt, cx, cy, cz, parent)
    for k in range(q0, qt):
        u = cq[k]
        c = parent[u]
        for j in range(fcnt[c]):
            fd[u, j, 0], fd[u, j, 1], fd[u, j, 2] = fd[c, j, 0], fd[c, j, 1], fd[c, j, 2]
            fdist[u, j] = fdist[c, j] + 1.0
        fcnt[u] = fcnt[c]
    seedless = 0
    for c in range(ncel):
        if cflag[c] != 0 and fcnt[c] == 0:
            seedless += 1
        if cflag[c] == 0:
            fcnt[c] = 0
    stats = np.array([n_leaf, n_crit, conflicts, seedless, n_face], np.int64)
    return state.reshape((nx, ny, nz)), fd, fdist, fcnt, stats


def _seed_lists(fd: np.ndarray, fdist: np.ndarray, fcnt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The seeds of every seed cell in one array, nearest first: ``seed_ptr`` (ncel + 1,) and ``seeds``
    (n, 3) from :func:`_build_map`'s per-cell tables (``fcnt[c]`` seeds of cell ``c`` in ``fd[c]``, their
    distances in ``fdist[c]``). A stable sort (ties keep the order they were found in); done here, not in
    the kernel, where a sort costs seconds of first-run compile."""
    S2 = fd.shape[1]
    used = np.arange(S2) < fcnt[:, None]
    key = np.where(used, fdist, np.inf)
    order = np.argsort(key, axis=1, kind="stable")
    seeds = np.take_along_axis(fd, order[:, :, None], axis=1)[used]  # used is a prefix of every row
    seed_ptr = np.zeros(len(fcnt) + 1, np.int64)
    np.cumsum(fcnt, out=seed_ptr[1:])
    return seed_ptr, np.ascontiguousarray(seeds)


# ============================================================================ the map of an arm
def _cache_key(arm) -> str:
    h = hashlib.sha256()
    h.update(MAP_VERSION.encode())
    for arr in arm.chain:
        a = np.ascontiguousarray(arr)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    h.update(repr(arm.map_params).encode())
    return h.hexdigest()

def _digest(arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()

def reach_map_of(arm) -> ReachMap:
    """``arm``'s reachability map from the disk cache, or built (and cached); its build statistics go to
    ``arm.map_info``."""
    key = _cache_key(arm)
    path = cache_dir() / f"reachmap-{key[:40]}.npz"
    t0 = time.perf_counter()
    rmap = _read_cache(arm, path, key)
    if rmap is not None:
        arm.map_info.update(from_cache=True, seconds=time.perf_counter() - t0, cache_file=str(path))
    else:
        rmap = build_map(arm)
        arm.map_info.update(from_cache=False, seconds=time.perf_counter() - t0)
        _write_cache(arm, path, key, rmap)
    st = rmap.state
    arm.map_info.update(h=rmap.h, shape=tuple(int(v) for v in rmap.shape), n_out=int((st == 0).sum()),
                         n_in=int((st == 1).sum()), n_boundary=int((st == 2).sum()),
                         n_seeds=int(len(rmap.seeds)))
    return rmap

def _read_cache(arm, path: Path, key: str) -> ReachMap | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            arrs = [np.array(z[f]) for f in ReachMap._fields]
            if str(z["digest"]) != _digest(arrs):
                return None
    except Exception:  # missing, truncated, not an npz, wrong fields: rebuild
        return None
    origin, h, shape, state, depth, sub, seed_ptr, seeds = arrs
    shape = shape.astype(np.int64)
    if (origin.shape != (3,) or h.shape != () or sub.shape != () or shape.shape != (3,)
            or state.dtype != np.uint8 or state.shape != tuple(shape) or int(sub) < 1
            or depth.dtype != np.uint8 or depth.shape != state.shape
            or not np.array_equal(depth == 0, state == 2)
            or np.any(shape % int(sub)) or seed_ptr.shape != (int(np.prod(shape // int(sub))) + 1,)
            or seeds.ndim != 2 or seeds.shape[1] != arm.n or seed_ptr[-1] != len(seeds)
            or np.any(np.diff(seed_ptr) < 0) or seed_ptr[0] != 0 or not np.isfinite(h) or h <= 0):
        return None
    return ReachMap(origin.astype(float), float(h), shape, np.ascontiguousarray(state), np.ascontiguousarray(depth),
                    int(sub), seed_ptr.astype(np.int64), np.ascontiguousarray(seeds, dtype=float))

def _write_cache(arm, path: Path, key: str, rmap: ReachMap) -> None:
    arrs = {f: np.asarray(getattr(rmap, f)) for f in ReachMap._fields}
    digest = _digest([arrs[f] for f in ReachMap._fields])
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".reachmap-", suffix=".npz", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, key=np.array(key), digest=np.array(digest), **arrs)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
    except OSError:  # an unwritable cache only costs a rebuild next time
        pass

def _lipschitz(arm) -> tuple[float, np.ndarray]:
    """K (bound on ||J(q) - J(q')|| / |q - q'|) and per-joint bounds on |J_i|."""
    ch, n = arm.chain, arm.n
    t = np.linalg.norm(ch.T[:, :3, 3], axis=1)
    pr = np.where(ch.jtype == 1, np.maximum(np.abs(ch.lo[:n]), np.abs(ch.hi[:n])), 0.0)
    R = np.array([t[j + 1:].sum() + pr[j + 1:].sum() for j in range(n)])
    b = np.zeros((n, n))
    for i in range(n):
        for k in range(n):
            a, c = min(i, k), max(i, k)
            if ch.jtype[a] == 0 and ch.jtype[c] == 0:
                b[i, k] = R[c]
            elif ch.jtype[a] == 0 and ch.jtype[c] == 1:
                b[i, k] = 1.0
    L = np.where(ch.jtype == 0, R, 1.0)
    return float(np.sqrt((b * b).sum())), L

def _faces(arm, wrap) -> np.ndarray:
    """The faces of Q as planar patches (f, 13): point c, tangents t1, t2 (joint space) and the
    ranges [u0, u1, v0, v1] of q = c + u t1 + v t2 that cover the face."""
    ch, n = arm.chain, arm.n
    out = []
    for r in range(ch.A.shape[0]):
        row = ch.A[r]
        if r < n and wrap[r]:
            continue
        d = int(np.argmax(np.abs(row)))
        a, b = [i for i in range(n) if i != d]
        for bound in (ch.lo[r], ch.hi[r]):
            c = np.zeros(n)
            c[d] = bound / row[d]
            t1 = np.zeros(n)
            t1[a], t1[d] = 1.0, -row[a] / row[d]
            t2 = np.zeros(n)
            t2[b], t2[d] = 1.0, -row[b] / row[d]
            out.append(np.concatenate([c, t1, t2, [ch.lo[a], ch.hi[a], ch.lo[b], ch.hi[b]]]))
    return np.array(out, float).reshape(-1, 13)

def _det_bound(arm) -> np.ndarray:
    """M (n, n): |d2 det J / dq_k dq_l| <= M[k, l] everywhere.

    Bounds for a serial chain: |J_j| <= L_j; |dJ_j/dq_k| <= b[j, k]; |d2 J_j/dq_k dq_l| <=
    R_max(j,k,l) (all revolute) or 1 (a prismatic joint involved): every derivative of a
    revolute chain rotates a vector about a unit axis, a prismatic one swaps a lever arm for
    a unit axis.
    """
    ch, n = arm.chain, arm.n
    t = np.linalg.norm(ch.T[:, :3, 3], axis=1)
    pr = np.where(ch.jtype == 1, np.maximum(np.abs(ch.lo[:n]), np.abs(ch.hi[:n])), 0.0)
    R = np.array([t[j + 1:].sum() + pr[j + 1:].sum() for j in range(n)])
    rev = ch.jtype == 0
    L = np.where(rev, R, 1.0)
    b = np.where(rev[:, None] & rev[None, :], R[np.maximum.outer(np.arange(n), np.arange(n))], 1.0)
    M = np.zeros((n, n))
    for k in range(n):
        for kk in range(n):
            tot = 0.0
            for j in range(n):
                others = [m for m in range(n) if m != j]
                # both derivatives on column j, or one on column j and one on column m
                b3 = R[max(j, k, kk)] if (rev[j] and rev[k] and rev[kk]) else 1.0
                tot += b3 * np.prod(L[others])
                for m in others:
                    third = [x for x in range(n) if x not in (j, m)][0]
                    tot += b[j, k] * b[m, kk] * L[third]
            M[k, kk] = tot
    return M

def build_map(arm) -> ReachMap:
    p = arm.map_params
    ch = arm.chain
    K, _ = _lipschitz(arm)
    jlo, jhi = arm.limits[:, 0].copy(), arm.limits[:, 1].copy()
    wrap = np.array([ch.jtype[i] == 0 and jhi[i] - jlo[i] >= TWO_PI - 1e-9 for i in range(arm.n)])
    # a first look at the workspace: extent (-> voxel size) and per-joint wrist speed
    g = [np.linspace(lo, hi, 13) for lo, hi in arm.limits]
    Qs = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, 3)
    Qs = Qs[arm.within_limits(Qs)]
    Ws = arm.forward(Qs)
    H = float(np.ptp(Ws, axis=0).max()) / p.voxels
    h = H / p.sub
    speed = np.linalg.norm(arm.jacobian(Qs), axis=1).max(axis=0) * 1.05 + 1e-9
    ncell = np.maximum(1, np.ceil((jhi - jlo) * speed / (p.coarse * H))).astype(np.int64)
    djoint = (jhi - jlo) / ncell
    bmin, bmax, _ = _coarse_bbox(ch, K, jlo, djoint, ncell)
    cshape = np.ceil((bmax - bmin) / H).astype(np.int64) + 2
    origin = 0.5 * (bmin + bmax) - 0.5 * H * cshape      # >= half a seed cell of margin
    shape = cshape * p.sub
    state, fd, fdist, fcnt, stats = _build_map(ch, K, _det_bound(arm), jlo, djoint, ncell, _faces(arm, wrap),
                                               origin, h, shape, p.sub, p.beta, p.max_depth, p.seeds, p.tau)
    seed_ptr, seeds = _seed_lists(fd, fdist, fcnt)
    arm.map_info.update(K=K, coarse_cells=int(np.prod(ncell)), leaves=int(stats[0]),
                         singular_leaves=int(stats[1]), face_patches=int(stats[4]), conflicts=int(stats[2]), seedless=int(stats[3]))
    return ReachMap(origin, h, shape, state, state_depth(state), int(p.sub), seed_ptr, seeds)


def state_depth(state: np.ndarray) -> np.ndarray:
    """:attr:`ReachMap.depth` of a voxel state array: per out or in voxel the chessboard distance to
    the nearest voxel of another state (scipy's distance transform, capped at 255), 0 on the boundary.
    The map's edge is not another state; a state with no other state in the map gets 255."""
    from scipy.ndimage import distance_transform_cdt

    depth = np.zeros(state.shape, np.uint8)
    for s in (0, 1):
        same = state == s
        if same.all():  # nothing else in the map: as far as the map reaches
            depth[...] = 255
            continue
        if same.any():
            d = distance_transform_cdt(same, metric="chessboard")
            depth[same] = np.minimum(d[same], 255)
    return depth


def base_offset(arm, source) -> np.ndarray | None:
    """The translation (3,) taking ``source``'s chain to ``arm``'s when the two differ only by the base's
    position (the same joints, limits, map parameters and base rotation, bit for bit); else None."""
    a, b = arm.chain, source.chain
    if arm.n != source.n or arm.map_params != source.map_params or a.T.shape != b.T.shape:
        return None
    same = (np.array_equal(a.T[0, :3, :3], b.T[0, :3, :3]) and np.array_equal(a.T[1:], b.T[1:])
            and all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("axis", "jtype", "A", "lo", "hi"))
            and np.array_equal(a.screw[:-1, :3], b.screw[:-1, :3]))
    if not same:
        return None
    delta = a.T[0, :3, 3] - b.T[0, :3, 3]
    pts_a = np.concatenate([a.screw[:-1, 3:], a.screw[-1:, :3]])
    pts_b = np.concatenate([b.screw[:-1, 3:], b.screw[-1:, :3]])
    scale = 1e-12 * max(1.0, float(np.abs(pts_a).max()), float(np.abs(pts_b).max()))
    return delta if np.allclose(pts_a - pts_b, delta, rtol=0.0, atol=scale) else None


def share_translated(arm, source) -> bool:
    """Give ``arm`` the reachability map of ``source`` moved with the base when the two arms differ only by
    the base's position (:func:`base_offset`): the reachable wrists translate with the base, the seeds (joint
    values) and every voxel's state stay, so the moved map holds every guarantee of a built one. Kept in
    memory and written to the disk cache under ``arm``'s own key (a worker process finds it there).
    False (nothing done) when the arms differ otherwise or ``arm`` has its map already."""
    if arm._rmap is not None:
        return False
    delta = base_offset(arm, source)
    if delta is None:
        return False
    src = source.reach_map()
    rmap = src._replace(origin=np.asarray(src.origin, float) + delta)
    arm._rmap = rmap
    key = _cache_key(arm)
    _write_cache(arm, cache_dir() / f"reachmap-{key[:40]}.npz", key, rmap)
    arm.map_info.update(from_cache=False, translated_from=tuple(float(v) for v in source.base_position), seconds=0.0,
                        h=rmap.h, shape=tuple(int(v) for v in rmap.shape))
    return True
