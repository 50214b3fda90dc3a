"""Dispatch: answer a scenario's ``[[tolerance]]`` tables, every size checked before the first runs."""
from __future__ import annotations

import math
import time

from ..errors import ErrplanError
from .insertion import (LIBERTY_ANGLE_RATIO, insertion_band, spatial_insertion_band, spatial_tracker_noise,
                        tracker_noise)
from .placement import check_placement, port_placement
from .region import TIP_BYTES, _extent, _grid_size, port_tolerance, region_text, tip_load_tolerance
from .result import Progress, ToleranceResult

#: P2's flexion controller at insertion depths (planar and in 3-D)
PLANAR_KINDS = ("insertion_band", "tracker_noise")


def run_query(sc, tol, progress: Progress | None = None, *, workers: int | None = 1,
              scheduler: str | None = None) -> ToleranceResult:
    """Answer one :class:`errplan.scenario.Tolerance` of scenario ``sc``. ``workers``/``scheduler``:
    where a ``port_placement`` query's candidates run (:func:`errplan.cluster.map_tasks`)."""
    t0 = time.perf_counter()
    o = tol.options
    gain = o.get("gain", sc.controller.gain)
    where = f"[[tolerance]] {tol.name!r}"
    try:
        if tol.kind == "port":
            data = port_tolerance(sc, o["region"], o.get("direction", "radial"), gain=gain,
                                  tip_force_over_ei=o.get("tip_force_over_ei"), spacing=o.get("spacing"),
                                  progress=progress)
        elif tol.kind == "tip_load":
            data = tip_load_tolerance(sc, o["region"], gain=gain, port_x=o.get("port_x"), port_y=o.get("port_y"),
                                      port_z=o.get("port_z"), spacing=o.get("spacing"), progress=progress)
        elif tol.kind == "port_placement" and o["candidates"] == "body_wall":
            from .wall import wall_port_placement

            data = wall_port_placement(sc, o["spacing"], o["region"], resolution=o.get("resolution"), gain=gain,
                                       certify_margin=o.get("certify_margin"), workers=workers, scheduler=scheduler,
                                       progress=progress)
        elif tol.kind == "port_placement":
            data = port_placement(sc, o["candidates"], o["spacing"], o["region"], resolution=o.get("resolution"),
                                  gain=gain, certify_margin=o.get("certify_margin"), refine=o.get("refine", False),
                                  refine_levels=o.get("refine_levels", 3), workers=workers, scheduler=scheduler,
                                  progress=progress)
        elif tol.kind == "insertion_band" and sc.dim == 3:
            sn = o["sensor_noise"]
            data = spatial_insertion_band(o.get("length", sc.instrument.length), _tip_load(o, where), sn.position,
                                          sn.angle, gain=gain, samples=o.get("samples", 97),
                                          shaft_direction=o.get("shaft_direction", (0.0, 0.0, 1.0)), progress=progress)
        elif tol.kind == "tracker_noise" and sc.dim == 3:
            data = spatial_tracker_noise(o.get("length", sc.instrument.length), _tip_load(o, where), o["band"],
                                         gain=gain, angle_ratio=o.get("angle_ratio", LIBERTY_ANGLE_RATIO),
                                         samples=o.get("samples", 21),
                                         shaft_direction=o.get("shaft_direction", (0.0, 0.0, 1.0)), progress=progress)
        elif tol.kind == "insertion_band":
            sn = o["sensor_noise"]
            data = insertion_band(o.get("length", sc.instrument.length), _tip_load(o, where), sn.position, sn.angle,
                                  gain=gain, samples=o.get("samples", 193), hold=o.get("hold", "tip_force"),
                                  shaft_angle=o.get("shaft_angle", 0.0), sampling=o.get("noise_sampling", "worst"),
                                  draws=o.get("draws", 10000), seed=o.get("seed", sc.planner.seed), progress=progress)
        elif tol.kind == "tracker_noise":
            data = tracker_noise(o.get("length", sc.instrument.length), _tip_load(o, where), o["band"], gain=gain,
                                 angle_ratio=o.get("angle_ratio", LIBERTY_ANGLE_RATIO), samples=o.get("samples", 41),
                                 hold=o.get("hold", "tip_force"), shaft_angle=o.get("shaft_angle", 0.0),
                                 progress=progress)
        else:  # pragma: no cover - the scenario parser rejects other kinds
            raise ErrplanError(f"{where}: unknown kind {tol.kind!r}")
    except ErrplanError as e:
        msg = str(e)
        raise type(e)(msg if msg.startswith(where) else f"{where}: {msg}") from None
    return ToleranceResult(tol.name, tol.kind, data, time.perf_counter() - t0)


def run_setup_query(st, tol, progress: Progress | None = None, *, workers: int | None = 1,
                    scheduler: str | None = None) -> ToleranceResult:
    """Answer one setup-level query (``triad_placement``, ``setup_placement``) of a
    :class:`errplan.scenario.Setup`."""
    from .setup import setup_placement
    from .triad import triad_placement

    t0 = time.perf_counter()
    where = f"[[tolerance]] {tol.name!r}"
    try:
        fn = setup_placement if tol.kind == "setup_placement" else triad_placement
        data = fn(st, tol, workers=workers, scheduler=scheduler, progress=progress)
    except ErrplanError as e:
        msg = str(e)
        raise type(e)(msg if msg.startswith(where) else f"{where}: {msg}") from None
    return ToleranceResult(tol.name, tol.kind, data, time.perf_counter() - t0)


def _tip_load(o: dict, where: str) -> float:
    t = o.get("tip_force_over_ei")
    if t is None:
        raise ErrplanError(f"{where}: tip_force_over_ei is required (P2's flexion controller needs a tip load)")
    if isinstance(t, (tuple, list)):
        raise ErrplanError(f"{where}: tip_force_over_ei = {list(t)}: expected one number for this kind")
    return float(t)


def check_sizes(sc) -> None:
    """Every size a scenario's ``[[tolerance]]`` queries will allocate, checked against the memory
    budget before any query runs (:func:`errplan.inputs.check_allocation`): the region grids of
    ``port`` and ``tip_load`` queries (from ``region`` and ``spacing``), the candidate budget and the
    task-region grid of ``port_placement`` queries, and the noise evaluations of ``insertion_band``
    queries (``samples`` x ``draws``)."""
    from ..inputs import check_allocation

    for tol in sc.tolerances:
        o = tol.options
        where = f"[[tolerance]] {tol.name!r}"
        region = o.get("region")
        if tol.kind in ("port", "tip_load") and region is not None:
            ext = _extent(region)
            h = float(o["spacing"]) if o.get("spacing") else ext / 8.0
            size = _grid_size(region, min(h, ext) if ext > 0 else 1.0)
            key, value = ((f"{where} spacing", h) if o.get("spacing") else (f"{where} region", region_text(region)))
            check_allocation(key, value, math.prod(size), TIP_BYTES,
                             f"the region grid ({' x '.join(f'{n:.3g}' for n in size)} tips)")
        if tol.kind == "port_placement":
            if o["candidates"] == "body_wall":  # the wall's candidates are counted when the anatomy is built
                check_placement(sc, dict(o, candidates={a: (0.0, 0.0) for a in sc.axes}, spacing=1.0), where)
            else:
                check_placement(sc, o, where)
        if tol.kind == "insertion_band" and o.get("noise_sampling") == "random":
            draws = o.get("draws", 10000)
            check_allocation(f"{where} draws", draws, draws, 6 * 8, "the noise draws")


def run_all(sc, progress: Progress | None = None, *, workers: int | None = 1,
            scheduler: str | None = None) -> list[ToleranceResult]:
    """Answer every ``[[tolerance]]`` query of ``sc`` in order."""
    if not sc.tolerances:
        raise ErrplanError(f"{sc.source}: the scenario has no [[tolerance]] queries")
    check_sizes(sc)  # every query's grid before the first query starts
    out = []
    for i, tol in enumerate(sc.tolerances):
        def sub(f, msg, i=i, tol=tol):
            progress((i + min(max(f, 0.0), 1.0)) / len(sc.tolerances), f"{tol.name}: {msg}")

        out.append(run_query(sc, tol, sub if progress else None, workers=workers, scheduler=scheduler))
    return out
