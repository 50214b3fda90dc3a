"""The corrected scenario: the scenario's own TOML with the found effects under ``[effects]``."""
from __future__ import annotations

import math

from ..errors import ErrplanError
from .report import CalibrationReport


# ----------------------------------------------------------------------------- scenario export
def _toml_key(k: str) -> str:
    import re

    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_str(k)


def _toml_str(s: str) -> str:
    out = ['"']
    for ch in s:
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\t":
            out.append("\\t")
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ErrplanError(f"cannot write the non-finite number {v} to TOML")
        return repr(v)
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if hasattr(v, "item"):
        return _toml_value(v.item())
    raise ErrplanError(f"cannot write {type(v).__name__} {v!r} to TOML")


def to_toml(doc: dict, header: str = "") -> str:
    """A TOML document for a parsed-TOML-like dict: tables as ``[a.b]`` sections, lists of
    tables as ``[[a]]`` (their sub-tables inline), everything else inline."""
    lines: list[str] = [f"# {h}" if h else "#" for h in header.splitlines()] if header else []

    def is_aot(v) -> bool:
        return isinstance(v, list) and len(v) > 0 and all(isinstance(x, dict) for x in v)

    def emit(table: dict, path: list[str], inline_tables: bool) -> None:
        for k, v in table.items():
            if (isinstance(v, dict) and not inline_tables) or is_aot(v):
                continue
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
        if not inline_tables:
            for k, v in table.items():
                if isinstance(v, dict):
                    sub = path + [_toml_key(k)]
                    if any(not isinstance(x, dict) for x in v.values()) or not v:
                        lines.append("")
                        lines.append(f"[{'.'.join(sub)}]")
                    emit(v, sub, False)
        for k, v in table.items():
            if is_aot(v):
                sub = path + [_toml_key(k)]
                for item in v:
                    lines.append("")
                    lines.append(f"[[{'.'.join(sub)}]]")
                    emit(item, sub, True)

    emit(doc, [], False)
    return "\n".join(lines).lstrip("\n") + "\n"


def corrected_scenario_toml(sc, report: CalibrationReport) -> str:
    """The corrected robot's scenario TOML (:func:`corrected_files`)."""
    return corrected_files(sc, report, None)[0]


def _read_doc(sc) -> dict:
    """The scenario's own TOML, re-read, with its URDF and package paths made absolute (the exported
    file may be written anywhere)."""
    from pathlib import Path

    import tomllib

    try:
        doc = tomllib.loads(Path(sc.source).read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ErrplanError(f"{sc.source}: cannot re-read the scenario to export it: {e}") from None
    robot = doc.get("robot")
    if sc.dim == 3 and isinstance(robot, dict):
        robot["urdf"] = str(sc.robot.urdf)
        if "package_path" in robot:
            robot["package_path"] = [str(x) for x in sc.robot.package_path]
    return doc


def _header(sc, report: CalibrationReport, what: str) -> str:
    found = ", ".join(report.selected) or "none"
    return (f"{sc.name}: {what}, by `errplan calibrate` on {report.data_source}\n"
            f"found effects: {found}; explained: {str(report.explained).lower()}\n"
            f"noise floor {report.noise.sigma:.3e} m; pose RMS {report.fit_errors.pose_before:.3e} -> "
            f"{report.fit_errors.pose_after:.3e} m")


def _effects_doc(effects: dict) -> dict:
    return {e: {p: float(v) for p, v in ps.items()} for e, ps in effects.items()}


def corrected_files(sc, report: CalibrationReport, path=None) -> tuple[str, dict]:
    """``--export-scenario``: the corrected robot, what a user runs from now on (docs/physics.md
    "From measured data to the plan"). Its TOML text and the other files it needs, ``{path: text}``.

    The controller and the truth both take what the fit found: ``link_length`` goes into ``[robot]
    link_lengths``, ``instrument_length`` into ``[instrument] length``, a URDF arm's ``joint_geometry``
    into a corrected URDF (joint origins changed, nothing else; every relative mesh path rewritten to
    resolve from its new folder; :func:`errplan.kinematics.geometry.corrected_urdf_text`) written beside
    the scenario ``path`` as ``<scenario stem>.urdf``, which the scenario's ``urdf`` names; a
    ``port_offset`` is folded into ``[port] position``, and when the fit found it the controller's
    ``estimate`` becomes that identified port (the ``[uncertainty]`` box stays the error set around
    it). ``tracker_registration`` and the physical effects stay under ``[effects]``: the truth has
    them, the controller does not model them."""
    from pathlib import Path

    import tomllib

    from ..kinematics import check_scenario
    from ..scenario import scenario_from_dict

    doc = _read_doc(sc)
    robot = doc.get("robot")
    effects = report.effects_table()
    from ..effects import latency_in_scenario_units  # tracker_latency's tau in the scenario's time unit

    effects, step_time = latency_in_scenario_units(effects, sc, getattr(report, "data", None))
    if step_time is not None:
        doc.setdefault("sensors", {})["step_time"] = step_time
    extra: dict = {}
    urdf_text = None
    if "link_length" in effects and isinstance(robot, dict):
        dl = effects.pop("link_length")
        ll = list(sc.robot.link_lengths)
        robot["link_lengths"] = [ll[0] + dl.get("dl1", 0.0), ll[1] + dl.get("dl2", 0.0)]
    if "instrument_length" in effects:
        dL = effects.pop("instrument_length").get("dL", 0.0)
        doc.setdefault("instrument", {})["length"] = float(sc.instrument.length + dL)
    if "port_offset" in effects and isinstance(doc.get("port"), dict):
        off = effects.pop("port_offset")
        axes = ("dx", "dy", "dz") if sc.dim == 3 else ("dy", "dz")
        port = [float(p + off.get(a, 0.0)) for p, a in zip(sc.port.position, axes)]
        doc["port"]["position"] = port
        if "port_offset" in report.selected:
            doc["port"]["estimate"] = list(port)
    if "joint_geometry" in effects and sc.dim == 3 and isinstance(robot, dict):
        from ..kinematics.geometry import corrected_urdf_text
        from ..effects import make_effect

        jg = effects.pop("joint_geometry")
        names = make_effect("joint_geometry", dim=3, n_joints=len(sc.robot.joints)).params
        src = Path(str(sc.robot.urdf))
        target = (Path(path).with_suffix(".urdf") if path is not None
                  else src.with_name(src.stem + "-calibrated.urdf"))
        if target.resolve() == src.resolve():
            target = target.with_name(target.stem + "-calibrated.urdf")
        urdf_text = corrected_urdf_text(src.read_text(encoding="utf-8"), sc.robot.joints,
                                        [jg.get(k, 0.0) for k in names], str(src), wrist=sc.robot.wrist,
                                        source_dir=src.parent, target_dir=target.parent)
        robot["urdf"] = str(target.resolve()) if path is None else target.name
        extra[str(target)] = urdf_text
    if effects:
        doc["effects"] = _effects_doc(effects)
    else:
        doc.pop("effects", None)
    doc["name"] = f"{sc.name}-calibrated" if report.selected else sc.name
    found = ", ".join(report.selected) or "none"
    doc["description"] = (sc.description + " | " if sc.description else "") + f"calibrated: {found}"
    text = to_toml(doc, _header(sc, report, "the corrected robot (controller and truth)"))
    if urdf_text is None:
        check_scenario(scenario_from_dict(tomllib.loads(text), "<exported scenario>"))  # reads back, or raises before writing
    else:  # read back with the corrected URDF in a scratch folder beside the target (its relative mesh paths
        # resolve as they will there): nothing is written where the user looks
        import tempfile

        tgt = Path(next(iter(extra))).resolve()
        try:
            tmp_ctx = tempfile.TemporaryDirectory(dir=tgt.parent, prefix=".errplan-export-")
        except OSError:
            tmp_ctx = tempfile.TemporaryDirectory()
        with tmp_ctx as tmp:
            d2 = tomllib.loads(text)
            (Path(tmp) / "robot.urdf").write_text(urdf_text, encoding="utf-8")
            d2["robot"]["urdf"] = str(Path(tmp) / "robot.urdf")
            _check_corrected_arm(scenario_from_dict(d2, "<exported scenario>"), report)
    return text, extra


def bench_files(sc, report: CalibrationReport) -> str:
    """``--export-bench``: the bench as it ran (docs/physics.md "From measured data to the plan"): the
    scenario as declared (its controller, arm, shaft, port estimate and error set unchanged) with the
    fitted truth under ``[effects]`` (every declared effect, the selected ones at their bench values,
    geometry included). Calibrating the same data on it selects nothing, and its "before" is this
    calibration's "after". The TOML text, read back before it is returned."""
    import tomllib

    from ..scenario import scenario_from_dict

    doc = _read_doc(sc)
    effects = report.effects_table()
    if effects:
        doc["effects"] = _effects_doc(effects)
    else:
        doc.pop("effects", None)
    doc["name"] = f"{sc.name}-bench"
    found = ", ".join(report.selected) or "none"
    doc["description"] = (sc.description + " | " if sc.description else "") + f"bench as calibrated: {found}"
    text = to_toml(doc, _header(sc, report, "the bench as it ran (declared controller, fitted truth)"))
    back = scenario_from_dict(tomllib.loads(text), "<exported bench>")
    if sc.dim == 3:
        _check_corrected_arm(back, report)
    else:
        from ..kinematics import check_scenario

        check_scenario(back)
    return text


def _check_corrected_arm(sc, report: CalibrationReport) -> None:
    """The exported scenario with its corrected URDF read back: the URDF loads with the scenario's
    joints and wrist, and the fit's own rows put the corrected wrist within the shaft's reach of the
    port and of its estimate (the bench ran there, so the port is reachable); only when they do not
    does the full check run, whose reachability map a new URDF would otherwise build from scratch
    (minutes for a six-joint arm)."""
    import numpy as np

    from ..kinematics import arm_for, check_scenario

    arm = arm_for(sc.robot)
    data = getattr(report, "data", None)
    if data is not None and len(data.q):
        w = np.asarray(arm.forward(data.q), float)
        L = sc.instrument.length
        if all(np.nanmin(np.linalg.norm(w - np.asarray(p, float), axis=-1)) < L
               for p in (sc.port.position, sc.port.estimate)):
            return
    check_scenario(sc)


def predictions_csv(sc, report: CalibrationReport, data) -> str:
    """``--predictions``: for every row of ``data``, the tracked tip the corrected model predicts at
    the row's encoder angles, noise-free (``run, step, tip_*``; friction's direction from the row's own
    run up to that row, as in the fit)."""
    import numpy as np

    from ..effects import predict_tracked
    from .residual import declared_plant, motion_model

    base = declared_plant(sc, data)  # a declared tracker_latency in the data's time unit
    u = data.commanded_directions(motion_model(sc))
    x = predict_tracked(report.model.plant(base), data.q, u, data.run, data.time)  # every row, dropouts too
    if report.empirical_predict is not None and not report.empirical["history_dependent"]:
        x = x + report.empirical_predict(x, data.q)
    axes = ("x", "y", "z")[3 - data.dim:]
    lines = ["run,step," + ",".join(f"tip_{a}" for a in axes)]
    for i in range(data.rows):
        lines.append(f"{data.run_ids[data.run[i]]},{int(data.step[i])}," + ",".join(repr(float(v)) for v in x[i]))
    return "\n".join(lines) + "\n"
