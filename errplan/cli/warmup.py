"""Compile in a second process what a command needs later.

A first run compiles errplan's kernels (numba, cached on disk: :mod:`errplan.jit`), and ``errplan demo``
needs the planar and the spatial ones while most of its own work (the URDF arm's reachability map, the
gains, the simulation) runs on one core. So when the cache is cold, :func:`start` launches
``python -m errplan.cli.warmup`` beside the command: a process that compiles the kernels of given parts, in
order, into the same disk cache and reports each part done. Before a step the command calls
:func:`wait` for that step's part, then loads the kernels from the cache instead of compiling them, and
it plans (a planner with a time budget) with the warm-up :func:`paused`, so that the plans of a first
run are those of any later one. A warm cache starts nothing; a failed or killed warm-up only means the
command compiles that part itself. ``ERRPLAN_WARMUP=0`` turns it off; it needs 2 cores.

Parts (each compiles, or loads, the kernels of one step at the argument types the step passes; a kernel
compiled here with other types, or not reached, is compiled again by every worker that calls it):
``fields2``/``fields3`` (the worst-case search with the exact |phi_max|, and the motion maps),
``fields2g``/``fields3g`` (the search without it: the planner's and the demo's spatial fields),
``lanes2``/``lanes3`` (the worst-||G|| refinement as lanes, for error sets without a load),
``plan2``/``plan3`` (the planner's cell walks), ``gains2`` (the planar kinematics the planar gains,
simulation and replays call: arm, flexed shaft, lever, 2 x 2 inverses), ``gains3`` (the 3-D gains: ``||I - k M||`` grids and their
bounded scan, worst instances, top-eigenvalue candidates, cuts, inverses, inverse kinematics), ``urdf`` (a URDF arm's kinematics and its reachability map's build: what
loading a spatial scenario compiles), ``arm`` (of those, all but the map's build),
``anatomy`` (the robust clearance of ``[anatomy]``: its scenario checks,
the planner's motion checks, the gains' and the replays' clearances).
"""
from __future__ import annotations

import atexit
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import time
from typing import Sequence

ENV = "ERRPLAN_WARMUP"

_STATE: dict = {"proc": None, "status": None, "parts": ()}


def _search_args(d: int, phi: bool = True) -> tuple:
    """Arguments of the compiled search of dimension ``d`` (those between the tips and the outputs of
    :func:`errplan.fields.kernels.worst_case_tile`), of the types :mod:`errplan.fields.compute` passes (a
    URDF arm's chain and reachability map are placeholders of the same numba types, so no scenario is
    needed)."""
    import numpy as np

    from ..fields.compute import EXTRA_PASSES, SECOND_START, _no_chain

    na = 3 if d == 2 else 5
    chain, rmap = _no_chain()
    f, b, v = np.zeros(na), np.zeros(na, bool), np.zeros(d)
    return (np.zeros((1, na)), np.ones(na, np.int64), b, b.copy(), f, f.copy(), f.copy(), v, v.copy(), 1.0, 1.0,
            np.zeros(16), chain, rmap, 1, EXTRA_PASSES, SECOND_START, phi, True)


def _fields(d: int, phi: bool = True) -> None:
    """The search (with the exact |phi_max| or without) and the motion maps of dimension ``d``, each run
    once on no tips (:func:`_search_args`)."""
    import numpy as np

    from ..fields.compute import _no_chain
    from ..fields.kernels import motion_maps, worst_case_tile

    na = 3 if d == 2 else 5
    chain, rmap = _no_chain()
    v, X = np.zeros(d), np.zeros((0, d))
    out = [np.zeros(0, bool)] + [np.zeros(0) for _ in range(4)]
    worst_case_tile(X, *_search_args(d, phi), *out)
    motion_maps(X, np.zeros((0, na)), v, v.copy(), 1.0, np.zeros(16), chain, rmap, np.zeros((0, d, d)),
                np.zeros(0, bool))


def _lanes(d: int) -> None:
    """The worst-||G|| refinement as lanes of dimension ``d`` (error sets without a load), run on none."""
    from ..fields.kernels import load_lanes

    load_lanes(d, *_search_args(d))


def _plan(d: int) -> None:
    """The planner's cell walks of dimension ``d``, each run once on a one-cell map with arguments of
    the types :mod:`errplan.planning` passes."""
    import numpy as np

    from ..planning import cellwalk as cw

    D = cw.pack(np.zeros(d), 1.0, (1,) * d, [np.zeros((1,) * d)] * 2 ** d, np.ones((1,) * d, bool), 1.0)
    o, P = [0.0] * d, np.zeros((1, d))
    walk, point, path = (cw.walk2, cw.point_ok2, cw.path_cost2) if d == 2 else (cw.walk3, cw.point_ok3, cw.path_cost3)
    walk(D, *o, *o, True, True)
    point(D, *o)
    path(D, P)
    cw.walk_many(D, P, P.copy(), True)


def _gains3() -> None:
    import numpy as np

    from .. import metrics
    from ..gains import physics

    M = np.zeros((0, 3, 3))
    physics.gnorm3_grid(M, [0.5])
    physics.gnorm3_pairs(M, 0.5)
    physics.cut_rows(M, 0.5)
    metrics.inv(M)
    metrics.spectral_norm(M)
    # the certificate's bounded gain scan and the verification's worst instances: their kernels run only
    # on some matrices (an empty batch returns before them), so on a few, as the gains pass them
    M4 = np.eye(3) + 0.1 * np.arange(36.0).reshape(4, 3, 3) / 36.0
    physics.grid_top(M4, np.linspace(0.1, 1.0, 4), 3)
    physics.worst_instances(M4.reshape(1, 4, 3, 3), np.ones((1, 4), bool), 0.5, False)
    physics.sym_top_candidates(M4 + M4.transpose(0, 2, 1))
    from ..fields.compute import _no_chain
    from ..kinematics.urdf.chain import _ik_many

    chain, rmap = _no_chain()
    W = np.zeros((0, 3))
    _ik_many(chain, rmap, W, np.zeros((0, 1)), False, np.zeros((0, 1)), np.zeros(0, np.bool_))


def _gains2() -> None:
    """The planar kinematics' compiled kernels (:mod:`errplan.kinematics.compiled` and the evaluator's true
    wrist): the arm's forward kinematics, Jacobian, reachability and inverse, the flexed shaft's geometry,
    Jacobian and wrist, the lever's parts and the 2 x 2 inverses, each run once on a few points of a planar
    arm (what the planar gains, simulation and replays call)."""
    import math

    import numpy as np

    from .. import metrics
    from ..fields.evaluator import _true_wrist2
    from ..kinematics import shaft
    from ..kinematics.arm import Arm

    arm = Arm(base=(0.21, -0.21), l1=0.21, l2=0.21, home=(0.0, -math.pi / 2), q1_limits=(-1.9, 1.2),
              q2_limits=(-0.7, 3.0), sum_limits=(-0.3, 3.5))
    q = np.array([[0.1, -1.2], [0.2, -1.0], [0.3, -0.9]])
    w = np.ascontiguousarray(arm.forward(q))  # C arrays, as the gains and replays pass them
    arm.jacobian(q), arm.reachable(w), arm.inverse(w)
    p, t = np.array([0.0, 0.1]), np.array([0.0, 0.01, -0.01])
    x = np.ascontiguousarray(shaft.flexed_tip(w, p, 0.3, t))
    shaft.flexed_jacobian(w, p, 0.3, t), shaft.flexed_wrist(x, p, 0.3, t)
    mu, nu = shaft.lever_parts(w, p, 0.3)
    metrics.inverse_parts(mu, nu), metrics.inverse_parts(mu.real, nu)
    metrics.inv2(arm.jacobian(q))
    ok = np.empty(len(x), bool)
    _true_wrist2(x, np.repeat(p[None], len(x), axis=0), t, 0.3, True, arm._reach_params(), np.empty_like(x), ok)


def _arm() -> None:
    """A URDF arm's forward kinematics, Jacobians and reachability test and the map's coarse bounding box,
    run once on nothing with a placeholder chain: what a spatial scenario's load and run call besides the
    map's build (their callees are the build's and the spatial search's too)."""
    import numpy as np

    from ..fields.compute import _no_chain
    from ..kinematics.urdf.chain import _fk_many, _jac_many, _reach_many
    from ..kinematics.urdf.reachmap import _coarse_bbox

    chain, rmap = _no_chain()
    Q = np.zeros((0, 3))
    _fk_many(chain, Q, np.zeros((0, 3)))
    _jac_many(chain, Q, np.zeros((0, 3, 3)))
    _reach_many(chain, rmap, np.zeros((0, 3)), np.zeros(0, np.bool_))
    v, n0 = np.zeros(3), np.zeros(3, np.int64)
    _coarse_bbox(chain, 1.0, v, v.copy(), n0)


def _urdf() -> None:
    """A URDF arm's kernels: forward kinematics, Jacobians, reachability, inverse kinematics and the
    reachability map's build, each run once on nothing with a placeholder chain of the types a real arm
    passes (the map kernels on an empty joint box)."""
    import numpy as np

    from ..fields.compute import _no_chain
    from ..kinematics.urdf.chain import _fk_many, _ik_many, _jac_many, _reach_many
    from ..kinematics.urdf.reachmap import _build_map, _coarse_bbox

    chain, rmap = _no_chain()
    Q, W = np.zeros((0, 3)), np.zeros((0, 3))
    _fk_many(chain, Q, np.zeros((0, 3)))
    _jac_many(chain, Q, np.zeros((0, 3, 3)))
    _reach_many(chain, rmap, W, np.zeros(0, np.bool_))
    _ik_many(chain, rmap, W, Q, True, Q.copy(), np.zeros(0, np.bool_))
    v, n0 = np.zeros(3), np.zeros(3, np.int64)
    _coarse_bbox(chain, 1.0, v, v.copy(), n0)
    _build_map(chain, 1.0, np.zeros((3, 3)), v, v.copy(), n0, np.zeros((0, 13)), v.copy(), 1.0,
               np.ones(3, np.int64), 1, 1.0, 1, 1, 1e-9)


def _anatomy() -> None:
    """The clearance kernels of :mod:`errplan.anatomy`, each run once on a small anatomy of every convex
    obstacle shape inside an ellipsoid body wall (a mesh's triangles are convex pieces of the same types;
    the mesh wall's kernels are compiled as callees of the batch)."""
    import numpy as np

    from ..anatomy.model import build
    from ..scenario import Anatomy, BodyWall, Obstacle

    an = Anatomy(0.004, (Obstacle("s", "sphere", center=(0.0, 0.0, 0.1), radius=0.01),
                         Obstacle("c", "capsule", a=(0.03, 0.0, 0.1), b=(0.05, 0.0, 0.1), radius=0.005),
                         Obstacle("b", "box", center=(-0.03, 0.0, 0.1), half_extents=(0.01, 0.01, 0.01))),
                 BodyWall("ellipsoid", center=(0.0, 0.0, 0.1), radii=(0.2, 0.2, 0.2)))
    m = build(an, np.array([[0.0, 0.0, -0.05], [0.001, 0.0, -0.05]]))
    a, b = np.array([[0.0, 0.05, 0.1]]), np.array([[0.0, 0.06, 0.12]])
    m.tip(a), m.motion(a, b, 0.001), m.tip_clear(a), m.motion_clear(a, b)
    m.motion_ok(*a[0], *b[0]), m.checker()(*a[0], *b[0])
    m.wall_depth(a), m.wall_gap(a[0]), m.inside(a)


_PARTS = {"fields2": lambda: _fields(2), "fields3": lambda: _fields(3), "fields2g": lambda: _fields(2, False),
          "fields3g": lambda: _fields(3, False), "lanes2": lambda: _lanes(2), "lanes3": lambda: _lanes(3),
          "plan2": lambda: _plan(2), "plan3": lambda: _plan(3),
          "gains2": _gains2, "gains3": _gains3, "anatomy": _anatomy, "urdf": _urdf, "arm": _arm}


def fields_part(sc, phi: bool) -> str | None:
    """The part that compiles the search of a scenario's fields (``phi``: with the exact |phi_max|), or
    None where its fields take the numpy path instead (a flexion controller, or effects on the true
    Jacobian: :func:`errplan.fields.compute_fields`)."""
    from ..errorset import error_set

    if sc.controller.jacobian != "rigid" or error_set(sc)[1]:
        return None
    return f"fields{sc.dim}{'' if phi else 'g'}"


def _cold(parts: Sequence[str]) -> bool:
    """Whether some entry kernel of ``parts`` has no entry in the disk cache (a first run)."""
    from ..jit import cached

    entries = []
    for p in parts:
        d = p[6] if p.startswith("fields") else p[-1]
        if p.startswith("fields"):
            from ..fields import kernels

            entries += [kernels._TILES[int(d), not p.endswith("g")]]
        elif p.startswith("lanes"):
            from ..fields import kernels

            entries += [kernels._LANE_TILES[int(d)]]
        elif p == "urdf":
            from ..kinematics.urdf import reachmap

            entries += [reachmap._build_map]
        elif p == "arm":
            from ..kinematics.urdf import chain, reachmap

            entries += [chain._fk_many, chain._jac_many, chain._reach_many, reachmap._coarse_bbox]
        elif p == "anatomy":
            from ..anatomy import distance

            entries += [distance.clearance_batch, distance.motion_clearance1]
        elif p.startswith("plan"):
            from ..planning import cellwalk

            entries += [getattr(cellwalk, f"walk{d}")]
        elif p == "gains2":
            from ..kinematics import compiled

            entries += [compiled._geometry2_kernel, compiled._reachable_kernel]
        else:
            from ..gains import physics

            entries += [physics._vsigma_rows]
    return not all(cached(e) for e in entries)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def start(parts: Sequence[str]) -> bool:
    """Start the warm-up of ``parts`` (in this order) if the cache is cold; True if it started."""
    if os.environ.get(ENV, "1") == "0" or _STATE["proc"] is not None or _cores() < 2 or not _cold(parts):
        return False
    fd, status = tempfile.mkstemp(prefix="errplan-warmup-", suffix=".txt")
    os.close(fd)
    env = dict(os.environ, **{ENV: "0", "ERRPLAN_COMPILE_NOTICE": "0"})
    try:
        proc = subprocess.Popen([sys.executable, "-m", "errplan.cli.warmup", status, *parts], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        os.unlink(status)
        return False
    _STATE.update(proc=proc, status=status, parts=tuple(parts))
    atexit.register(stop)
    return True


def _done() -> set[str]:
    try:
        with open(_STATE["status"], encoding="utf-8") as f:
            return {line.split()[0] for line in f if line.endswith("\n") and line.strip()}
    except OSError:
        return set()


def active() -> bool:
    """Whether a warm-up is running (a first run)."""
    proc = _STATE["proc"]
    return proc is not None and proc.poll() is None


def load_here(parts: Sequence[str]) -> None:
    """The kernels of ``parts`` in this process (each waited for, then loaded from the disk cache): for a
    process about to fork workers that all call them, so that each does not load them again."""
    for p in parts:
        wait(p)
        _PARTS[p]()


def ready(part: str) -> bool:
    """Whether :func:`wait` for ``part`` would return at once (no warm-up, a part it does not do, done, or
    the warm-up has exited)."""
    proc = _STATE["proc"]
    return proc is None or part not in _STATE["parts"] or part in _done() or proc.poll() is not None


def wait(part: str, timeout: float = 900.0) -> None:
    """Block until the warm-up has done ``part`` (returns at once without a warm-up, for a part it does
    not do, or once it has exited)."""
    proc = _STATE["proc"]
    if proc is None or part not in _STATE["parts"]:
        return
    t_end = time.monotonic() + timeout
    while part not in _done() and proc.poll() is None and time.monotonic() < t_end:
        time.sleep(0.05)


@contextlib.contextmanager
def paused():
    """The warm-up stopped meanwhile (SIGSTOP/SIGCONT): for a step whose result depends on the CPU time
    it gets (the planner runs for a time budget), so that a first run plans exactly like a later one."""
    proc = _STATE["proc"]
    stop_sig = getattr(signal, "SIGSTOP", None)
    if proc is None or stop_sig is None or proc.poll() is not None:
        yield
        return
    proc.send_signal(stop_sig)
    try:
        yield
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGCONT)


def stop() -> None:
    """End the warm-up (at exit: a command that failed early leaves no process behind)."""
    proc, status = _STATE["proc"], _STATE["status"]
    if proc is not None and proc.poll() is None:
        proc.send_signal(getattr(signal, "SIGCONT", signal.SIGTERM))
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
    if status:
        try:
            os.unlink(status)
        except OSError:
            pass
    _STATE.update(proc=None, status=None, parts=())


def main(argv: Sequence[str]) -> int:
    """``python -m errplan.cli.warmup STATUS PART...``: do the parts in order, appending each name to STATUS
    when done (a failed part is reported done too: the command then compiles it itself)."""
    status, parts = argv[0], argv[1:]
    parent = os.getppid()
    t0 = time.perf_counter()
    for p in parts:
        if os.getppid() != parent:  # the command is gone
            return 0
        try:
            _PARTS[p]()
        except Exception:  # best effort: the command compiles what is missing
            pass
        with open(status, "a", encoding="utf-8") as f:
            f.write(f"{p} {time.perf_counter() - t0:.1f}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
