"""Setup placement (tolerance kind ``setup_placement``): where the instrument arms stand, chosen with the port
triad (docs/physics.md "Where the arms stand: setup placement").

A setup is a triad whose instrument candidates are (base, port) pairs: per instrument arm every base of
its ``bases`` (a list of poses or a grid, read by the scenario) with every port candidate of the triad
query (the union over the bases of the wall points the shaft reaches through from each). The search is
the triad's (:func:`errplan.tolerance.triad.place`), unchanged: coverage per (arm, base, port) once, on the
fields' kernels with the arm's base moved (the arm's scenario with that base, its model built once per
base); the bound LB(p1, p2) per pair of candidates, admissible because the hard constraints only remove
setups and the bases enter S only through coverage; pairs as tasks on ``--workers`` or a dask cluster.
Besides the triad's hard constraints:

- the arms at rest (each at the inverse kinematics putting its wrist on the shaft from its ``rest`` tip
  through its candidate port) at least ``[setup] arm_clearance`` apart (arm checks on);
- with ``[setup] patient_clearance``: every link of each arm (the URDF's collision objects, not the
  instrument shaft) at least that far from the body solid (:mod:`errplan.kinematics.urdf.collision`) at every
  covered target and at rest, by coal's distance.

Ties of S (frequent: two bases with the same coverage give the same score) go to the larger smallest arm
clearance over the covered targets and at rest (arm checks on), then the candidate indices.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ErrplanError
from .result import Progress


def body_solid(sc):
    """The patient's body of scenario ``sc`` (:class:`errplan.kinematics.urdf.collision.BodySolid`): its
    ellipsoid wall, or its mesh wall's convex hull; None without ``[anatomy.body_wall]``."""
    from ..fields.compute import anatomy_model
    from ..kinematics.urdf.collision import BodySolid

    m = anatomy_model(sc)
    if m is None or not m.wall[6] > 0:
        return None, m
    if m.mesh_wall:
        return BodySolid.hull(m.wall_surface[0]), m
    return BodySolid.ellipsoid(m.wall[:3], m.wall[3:6]), m


def setup_placement(st, tol, *, workers: int | None = 1, scheduler: str | None = None,
                    progress: Progress | None = None, prune: bool = True, keep: int = 6) -> dict[str, Any]:
    """Answer a ``setup_placement`` query of setup ``st``: the best setup (bases and ports) and the next
    ``keep - 1``, with the JSON keys of docs/interfaces.md."""
    from .triad import place

    o = tol.options
    where = "setup_placement"
    bases = o["bases"]
    n1, n2 = o["instruments"]
    body, model = body_solid(st.arm(n1))
    for name in (n1, n2):
        if not bases.get(name):
            raise ErrplanError(f"{where} bases.{name}: expected a non-empty list of base candidates")
        if model is not None and model.wall[6] > 0:
            depth = model.wall_depth(np.array([p for p, _ in bases[name]], float))
            for j, d in enumerate(depth):
                if d > 0:
                    raise ErrplanError(f"{where} bases.{name}[{j}].position = {list(bases[name][j][0])}: expected a "
                                       f"base outside the patient's body (it lies {1000 * d:.1f} mm inside the body "
                                       "wall)")
    pc = st.patient_clearance
    patient = None
    if pc is not None:
        if body is None:
            raise ErrplanError(f"[setup] patient_clearance = {pc:g}: needs an [anatomy.body_wall] (the patient's body)")
        patient = (body, float(pc))
    return place(st, tol, bases, workers=workers, scheduler=scheduler, progress=progress, prune=prune, keep=keep,
                 patient=patient)


# ============================================================================= the exported scenario
def _absolute(value: str, base_dir: Path) -> str:
    return value if value.startswith("package://") or Path(value).is_absolute() else str((base_dir / value).resolve())


def exported_document(doc: dict, source: str, data: dict) -> dict:
    """The scenario document ``doc`` (parsed from ``source``) with the best setup of a ``setup_placement``
    result ``data``: each instrument arm's ``base_position``/``base_rpy`` and port (the estimate at the chosen
    port, the true port moved with it), the endoscope's port likewise; relative file paths made absolute
    (the file may be written elsewhere). The other tables are kept as they are."""
    import copy

    out = copy.deepcopy(doc)
    base_dir = Path(source).resolve().parent
    best = data["best"]
    names = [a.get("name") for a in out.get("arm", [])]
    for name in data["instruments"]:
        a = out["arm"][names.index(name)]
        robot = a["robot"]
        b = best["bases"][name]
        robot["base_position"] = [float(v) for v in b["position"]]
        robot["base_rpy"] = [float(v) for v in b["rpy"]]
        a["port"] = _moved_port(a.get("port", {}), best["ports"][name])
    if "endoscope" in out:
        out["endoscope"]["port"] = _moved_port(out["endoscope"].get("port", {}), best["ports"]["endoscope"])
    for a in out.get("arm", []):
        r = a.get("robot", {})
        if isinstance(r.get("urdf"), str):
            r["urdf"] = _absolute(r["urdf"], base_dir)
        if isinstance(r.get("package_path"), list):
            r["package_path"] = [_absolute(x, base_dir) for x in r["package_path"]]
        elif isinstance(r.get("package_path"), str):
            r["package_path"] = _absolute(r["package_path"], base_dir)
    an = out.get("anatomy", {})
    if isinstance(an.get("body_wall"), dict) and isinstance(an["body_wall"].get("file"), str):
        an["body_wall"]["file"] = _absolute(an["body_wall"]["file"], base_dir)
    for ob in an.get("obstacle", []) if isinstance(an.get("obstacle"), list) else []:
        if isinstance(ob.get("file"), str):
            ob["file"] = _absolute(ob["file"], base_dir)
    return out


def _moved_port(port: dict, estimate) -> dict:
    est_old = port.get("estimate", port.get("position"))
    pos_old = port.get("position", est_old)
    est = [float(v) for v in estimate]
    out = dict(port, estimate=est)
    if est_old is not None and pos_old is not None:  # the truth keeps its offset from the estimate
        out["position"] = [e + (p - q) for e, p, q in zip(est, pos_old, est_old)]
    else:
        out["position"] = est
    return out


def export_header(name: str, data: dict) -> str:
    b = data["best"]
    return (f"exported by errplan tolerance --export-scenario: the best setup of {name!r}\n"
            f"(score {b['score']:.6g}, coverage of both instruments {100 * b['coverage']['both']:.1f} %); "
            "the chosen bases and port estimates replace the scenario's own")


def check_export(path, queries) -> Any:
    """The one ``setup_placement`` query (or result) to export (one clear error when there is none or
    several)."""
    setups = [r for r in queries if r.kind == "setup_placement"]
    if len(setups) != 1:
        raise ErrplanError(f"--export-scenario {path}: expected exactly one setup_placement query in the scenario, "
                           f"found {len(setups)}")
    return setups[0]


__all__ = ["setup_placement", "body_solid", "exported_document", "export_header", "check_export"]
