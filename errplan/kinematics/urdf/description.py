"""Reading a URDF into a chain: the file checked (XML, a tree, real axes), pinocchio's model, the actuated
joints, held joints, limits and the base placement turned into :class:`~.model.ChainData`. Pinocchio
parses the kinematic model only (meshes are never loaded, so missing meshes never fail kinematics)."""
from __future__ import annotations

import contextlib
import math
import os
import re
import sys
import tempfile
import xml.etree.ElementTree as ET
from xml.parsers import expat
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ...errors import ScenarioError
from ...inputs import read_bytes
from ...scenario import CoupledLimit
from .model import ChainData, MapParams, chain_screws


def rpy_matrix(rpy) -> np.ndarray:
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _se3(M) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(M.rotation)
    T[:3, 3] = np.asarray(M.translation)
    return T


@contextlib.contextmanager
def _captured_stderr():
    """Capture what C++ libraries (urdfdom) print on file descriptor 2; yields a callable giving it."""
    buf = tempfile.TemporaryFile(mode="w+b")
    saved = None
    try:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(buf.fileno(), 2)
    except OSError:  # no usable fd 2: nothing to capture
        saved = None
    text: list[str] = []
    try:
        yield lambda: "".join(text)
    finally:
        if saved is not None:
            os.dup2(saved, 2)
            os.close(saved)
        buf.seek(0)
        text.append(buf.read().decode("utf-8", "replace"))
        buf.close()


def _urdfdom_reason(log: str) -> str:
    for line in log.splitlines():
        line = line.strip()
        if line.startswith("Error:"):
            return line[len("Error:"):].strip()
    return ""


def _joint_kind(shortname: str) -> str:
    if re.search(r"RevoluteUnbounded|JointModelRUB[XYZ]$", shortname):
        return "continuous"
    if re.search(r"Revolute|JointModelR[XYZ]$", shortname):
        return "revolute"
    if re.search(r"Prismatic|JointModelP[XYZ]$", shortname):
        return "prismatic"
    if re.search(r"FreeFlyer", shortname):
        return "floating"   # the URDF's name for it
    return re.sub(r"^JointModel", "", shortname).lower()


def _finite_tuple(value, n: int, what: str, where: str) -> tuple[float, ...]:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ScenarioError(f"{where}: {what} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ScenarioError(f"{where}: {what} must be {n} finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


def _refuse_entities(raw: bytes, where: str) -> None:
    """A URDF declares no XML entities: a file that does is refused at the first declaration, before
    anything is expanded (an entity-expansion bomb never grows, whatever expat's own limits)."""
    parser = expat.ParserCreate()

    def declared(name, *_):
        raise ScenarioError(f"URDF {where} declares the XML entity '{name}' (<!ENTITY>): a URDF uses none; "
                            "refused, entities can expand without bound")

    parser.EntityDeclHandler = declared
    try:
        parser.Parse(raw, True)
    except expat.ExpatError:
        pass  # not XML: ElementTree names the error


def _three_numbers(text: str) -> list[float] | None:
    """The 3 finite numbers of a URDF vector attribute (``xyz``, ``rpy``), or None."""
    try:
        v = [float(t) for t in text.split()]
    except ValueError:
        return None
    return v if len(v) == 3 and all(math.isfinite(x) for x in v) else None


def _check_vectors(root, where: str) -> None:
    """Every ``origin`` (xyz, rpy) of a joint or link and every joint ``axis`` (xyz): 3 finite numbers. urdfdom
    rejects most bad ones without naming the joint or link; this names it."""
    for kind in ("joint", "link"):
        for el in root.iter(kind):
            for sub in el.iter():
                attrs = {"origin": ("xyz", "rpy"), "axis": ("xyz",)}.get(sub.tag, ()) if sub is not el else ()
                for attr in attrs:
                    text = sub.get(attr)
                    if text is not None and _three_numbers(text) is None:
                        raise ScenarioError(f"{where}: {kind} '{el.get('name', '?')}' has <{sub.tag} {attr}=\"{text}\">: "
                                            "expected 3 finite numbers")


def _check_tree(root, where: str) -> None:
    """What urdfdom and pinocchio let through or report misleadingly: origins and axes that are not 3 finite
    numbers (:func:`_check_vectors`), a joint naming a link that is not declared, a link with two parent
    joints (a URDF is a tree) and a movable joint whose axis is not a direction. One :class:`ScenarioError` each, naming the joint or link."""
    _check_vectors(root, where)
    links = {link.get("name") for link in root.findall("link")}
    for j in root.findall("joint"):
        for end in ("parent", "child"):
            el = j.find(end)
            if el is not None and el.get("link") is not None and el.get("link") not in links:
                raise ScenarioError(f"{where}: joint '{j.get('name', '?')}' names the {end} link '{el.get('link')}', "
                                    "which is not a <link> of the URDF")
    parents: dict[str, list[str]] = {}
    for j in root.iter("joint"):
        name = j.get("name", "?")
        child = j.find("child")
        if child is not None and child.get("link"):
            parents.setdefault(child.get("link"), []).append(name)
        axis = j.find("axis")
        if axis is None or j.get("type") in ("fixed", "floating"):
            continue
        xyz = _three_numbers(axis.get("xyz") or "1 0 0")
        if xyz is not None and math.hypot(*xyz) < 1e-12:
            raise ScenarioError(f"{where}: joint '{name}' has a zero axis (xyz = \"{axis.get('xyz')}\"): "
                                "expected a direction")
    for link, js in parents.items():
        if len(js) > 1:
            raise ScenarioError(f"{where}: link '{link}' has {len(js)} parent joints ({', '.join(js)}): a URDF is a "
                                "tree, each link the child of one joint")


def _float_or_nan(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def read_chain(urdf: str | Path, joints: Sequence[str], wrist: str, base_position=(0.0, 0.0, 0.0),
               base_rpy=(0.0, 0.0, 0.0), joint_limits=None, fixed_joints: Mapping[str, float] = {},
               coupled_limits: Sequence[CoupledLimit] = (), package_path: Sequence[str] = (),
               map_params: MapParams | None = None) -> tuple[dict, str]:
    """Read the URDF and describe the chain from the root to the ``wrist`` link: the keyword arguments of
    :class:`~.arm.UrdfArm` and the file's name for messages.

    Raises :class:`ScenarioError` (one line naming the file and the offending value) for a
    missing or unreadable file, text that is not a URDF, unknown or misplaced joints, a
    missing wrist link, joints that are not revolute/continuous/prismatic, and bad limits.
    """

    import pinocchio as pin

    path = Path(urdf)
    where = str(path)
    raw = read_bytes(path, "URDF file", ScenarioError)
    _refuse_entities(raw, where)
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as exc:
        raise ScenarioError(f"URDF {where} is not XML ({exc})") from None
    if root.tag != "robot":
        raise ScenarioError(f"URDF {where} is not a URDF: its root element is <{root.tag}>, expected <robot>")
    _check_tree(root, where)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ScenarioError(f"URDF {where} is not UTF-8 text") from None
    with _captured_stderr() as log:
        try:
            model = pin.buildModelFromXML(text)
            err = None
        except Exception as exc:  # pinocchio/urdfdom: ValueError, RuntimeError
            err = exc
    if err is not None:
        reason = _urdfdom_reason(log()) or str(err).splitlines()[0]
        raise ScenarioError(f"URDF {where} is not a valid URDF: {reason}")

    # ---- names
    joints = [joints] if isinstance(joints, str) else list(joints)
    if not all(isinstance(j, str) for j in joints):
        raise ScenarioError(f"{where}: joints must be joint names, got {joints!r}")
    if not isinstance(wrist, str):
        raise ScenarioError(f"{where}: wrist must be a link name, got {wrist!r}")
    body_frames = {f.name: k for k, f in enumerate(model.frames) if f.type == pin.FrameType.BODY}
    fixed_frames = {f.name for f in model.frames if f.type == pin.FrameType.FIXED_JOINT}
    if wrist not in body_frames:
        raise ScenarioError(f"{where}: wrist link '{wrist}' is not in the URDF "
                            f"(links: {', '.join(sorted(body_frames))})")
    jnames = list(model.names)
    all_joint_names = sorted(set(jnames[1:]) | (fixed_frames - {"universe"}))
    for j in joints:
        if j in fixed_frames:
            raise ScenarioError(f"{where}: joint '{j}' is fixed; actuated joints must be revolute, "
                                "continuous or prismatic")
        if j not in jnames[1:]:
            raise ScenarioError(f"{where}: joint '{j}' is not in the URDF (joints: {', '.join(all_joint_names)})")
    if len(set(joints)) != len(joints):
        raise ScenarioError(f"{where}: joints {joints} name a joint twice")
    wf = model.frames[body_frames[wrist]]
    chain_ids: list[int] = []
    jid = wf.parentJoint
    while jid != 0:
        chain_ids.append(jid)
        jid = model.parents[jid]
    chain_ids.reverse()
    chain_names = [jnames[i] for i in chain_ids]
    root_name = model.frames[1].name if len(model.frames) > 1 else "root"
    for j in joints:
        if j not in chain_names:
            raise ScenarioError(f"{where}: joint '{j}' is not on the chain from the root link '{root_name}' "
                                f"to the wrist link '{wrist}' (that chain: {', '.join(chain_names) or 'none'})")
    for jid in chain_ids:
        kind = _joint_kind(model.joints[jid].shortname())
        if kind not in ("revolute", "continuous", "prismatic"):
            raise ScenarioError(f"{where}: joint '{jnames[jid]}' on the chain to '{wrist}' is {kind}; "
                                "only revolute, continuous, prismatic and fixed joints can be on it")
    order = [chain_names.index(j) for j in joints]
    if order != sorted(order):
        raise ScenarioError(f"{where}: joints {joints} must be listed from the root to the wrist "
                            f"({', '.join(c for c in chain_names if c in joints)})")
    if len(joints) != 3:
        raise ScenarioError(f"{where}: {len(joints)} actuated joint(s) {joints} cannot place the wrist in 3-D; "
                            "exactly 3 are needed")
    fixed_joints = dict(fixed_joints or {})
    held = {}
    for name, val in fixed_joints.items():
        if name in joints:
            raise ScenarioError(f"{where}: fixed_joints names '{name}', which is an actuated joint")
        if name not in chain_names:
            raise ScenarioError(f"{where}: fixed_joints names '{name}', which is not a movable joint on the chain "
                                f"from '{root_name}' to '{wrist}' ({', '.join(c for c in chain_names if c not in joints) or 'none'})")
        v = _float_or_nan(val)
        if not math.isfinite(v):
            raise ScenarioError(f"{where}: fixed_joints value of '{name}' must be a finite number, got {val!r}")
        held[name] = v
    held_all = {name: held.get(name, 0.0) for name in chain_names if name not in joints}
    base_position = _finite_tuple(base_position, 3, "base_position", where)
    base_rpy = _finite_tuple(base_rpy, 3, "base_rpy", where)
    act_ids = [model.getJointId(j) for j in joints]
    kinds = [_joint_kind(model.joints[i].shortname()) for i in act_ids]

    # ---- limits
    if joint_limits is None:
        lims = []
        for j, jid, kind in zip(joints, act_ids, kinds):
            if kind == "continuous":
                lims.append((-math.pi, math.pi))
                continue
            iq = model.joints[jid].idx_q
            lo, hi = float(model.lowerPositionLimit[iq]), float(model.upperPositionLimit[iq])
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ScenarioError(f"{where}: joint '{j}' has no finite limits in the URDF; give joint_limits")
            if lo > hi:
                raise ScenarioError(f"{where}: joint '{j}' has reversed limits in the URDF: lower {lo} > upper {hi}")
            if lo == hi:
                raise ScenarioError(f"{where}: joint '{j}' has an empty range in the URDF: lower = upper = {lo}")
            lims.append((lo, hi))
    else:
        try:
            arr = np.asarray(joint_limits, dtype=float)
        except (TypeError, ValueError):
            raise ScenarioError(f"{where}: joint_limits must be {len(joints)} pairs [lo, hi], got {joint_limits!r}") from None
        if arr.shape != (len(joints), 2) or not np.all(np.isfinite(arr)):
            raise ScenarioError(f"{where}: joint_limits must be {len(joints)} finite pairs [lo, hi], got {joint_limits!r}")
        for j, (lo, hi) in zip(joints, arr):
            if lo > hi:
                raise ScenarioError(f"{where}: joint_limits for '{j}' are reversed: [{lo}, {hi}]")
            if lo == hi:
                raise ScenarioError(f"{where}: joint_limits for '{j}' are an empty range: [{lo}, {hi}]")
        lims = [(float(a), float(b)) for a, b in arr]
    rows = [np.eye(len(joints))[i] for i in range(len(joints))]
    lo_r = [a for a, _ in lims]
    hi_r = [b for _, b in lims]
    coupled = []
    for cl in coupled_limits or ():
        cj = tuple(getattr(cl, "joints", ()))
        cc = tuple(getattr(cl, "coeffs", ()))
        desc = f"coupled limit {list(cj)}"
        if len(cj) == 0 or len(cj) != len(cc):
            raise ScenarioError(f"{where}: {desc} needs one coefficient per joint, got coeffs {list(cc)}")
        row = np.zeros(len(joints))
        for name, coef in zip(cj, cc):
            if name not in joints:
                raise ScenarioError(f"{where}: {desc} names '{name}', which is not an actuated joint {joints}")
            c = _float_or_nan(coef)
            if not math.isfinite(c):
                raise ScenarioError(f"{where}: {desc} has a bad coefficient {coef!r}")
            row[joints.index(name)] += c
        try:
            lo, hi = float(cl.lo), float(cl.hi)
        except (TypeError, ValueError):
            lo = hi = float("nan")
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ScenarioError(f"{where}: {desc} bounds must be finite numbers, got [{cl.lo!r}, {cl.hi!r}]")
        if lo > hi:
            raise ScenarioError(f"{where}: {desc} bounds are reversed: [{lo}, {hi}]")
        if not np.any(row):
            raise ScenarioError(f"{where}: {desc} has all-zero coefficients")
        rows.append(row)
        lo_r.append(lo)
        hi_r.append(hi)
        coupled.append(CoupledLimit(cj, tuple(float(c) for c in cc), lo, hi))

    # ---- reference configuration: actuated 0, held joints at their values
    qref = pin.neutral(model)

    def set_joint(q, jid, val):
        jm = model.joints[jid]
        if jm.nq == 1:
            q[jm.idx_q] = val
        else:  # continuous: (cos, sin)
            q[jm.idx_q], q[jm.idx_q + 1] = math.cos(val), math.sin(val)

    for name, val in held_all.items():
        set_joint(qref, model.getJointId(name), val)
    data = model.createData()
    pin.forwardKinematics(model, data, qref)
    pin.updateFramePlacements(model, data)
    pin.computeJointJacobians(model, data, qref)
    B = np.eye(4)
    B[:3, :3] = rpy_matrix(base_rpy)
    B[:3, 3] = base_position
    oMi = [_se3(data.oMi[i]) for i in act_ids]
    T = np.empty((4, 4, 4))
    T[0] = B @ oMi[0]
    for i in range(1, 3):
        T[i] = np.linalg.solve(oMi[i - 1], oMi[i])
    T[3] = np.linalg.solve(oMi[2], _se3(data.oMf[body_frames[wrist]]))
    axes = np.empty((3, 3))
    jtype = np.empty(3, np.int64)
    for k, (jid, kind) in enumerate(zip(act_ids, kinds)):
        S = np.asarray(pin.getJointJacobian(model, data, jid, pin.ReferenceFrame.LOCAL))[:, model.joints[jid].idx_v]
        if kind == "prismatic":
            ax, jtype[k] = S[:3], 1
        else:
            ax, jtype[k] = S[3:], 0
        axes[k] = ax / np.linalg.norm(ax)
    chain = ChainData(np.ascontiguousarray(T), axes, jtype, np.ascontiguousarray(np.array(rows, float)),
                      np.array(lo_r, float), np.array(hi_r, float), chain_screws(T, axes))

    # ---- drawing points (joint and fixed-joint origins on the chain), per moving segment
    path_frames = []
    fid = body_frames[wrist]
    while fid != 0:
        f = model.frames[fid]
        if f.type in (pin.FrameType.JOINT, pin.FrameType.FIXED_JOINT):
            path_frames.append(fid)
        fid = f.parentFrame
    path_frames.reverse()
    n_before = {jid: sum(1 for a in act_ids if a in chain_ids[: chain_ids.index(jid)]) for jid in chain_ids}
    n_before[0] = 0
    segments: list[list[np.ndarray]] = [[np.array(base_position)]] + [[] for _ in range(3)]
    for fid in path_frames:
        f = model.frames[fid]
        pj = f.parentJoint
        s = n_before[pj] + (1 if f.type == pin.FrameType.FIXED_JOINT and pj in act_ids else 0)
        pos = np.append(np.asarray(data.oMf[fid].translation), 1.0)
        local = (B @ pos)[:3] if s == 0 else np.linalg.solve(oMi[s - 1], pos)[:3]
        if not any(np.allclose(x, local, rtol=0, atol=1e-12) for x in segments[s]):
            segments[s].append(local)
    segments[3] = [x for x in segments[3] if not np.allclose(x, T[3][:3, 3], rtol=0, atol=1e-12)]

    return dict(urdf_path=path.resolve(), urdf_text=text, model=model, joint_names=joints, wrist=wrist,
                chain=chain, base_position=base_position, base_rpy=base_rpy, coupled=coupled,
                fixed_values=held, package_path=[str(p) for p in (package_path or ())], act_ids=act_ids,
                qref=qref, segments=[np.array(s).reshape(-1, 3) for s in segments],
                map_params=map_params or MapParams()), where
