"""Geometric errors of the arm (docs/physics.md "Closing the loop when the catalogue lacks the effect"):
the arm whose geometry differs from its description.

- Planar P1 arm: ``link_length`` ``[dl1, dl2]`` adds to the link lengths (:func:`perturbed_arm`).
- URDF arm: ``joint_geometry``, per actuated joint i ``[dx_i, dy_i, dz_i, rx_i, ry_i, rz_i]``: the
  joint's ``<origin>`` in its parent link's frame ``O = [R0, p0]`` becomes ``[R(r) R0, p0 + d]``
  (``R(r)`` the rotation by the rotation vector ``r``), before the joint's motion. With the chain's
  fixed transforms ``T[i] = P_i O_i`` (:class:`~errplan.kinematics.urdf.model.ChainData`; ``P_i``
  the fixed path from the previous actuated joint's child frame, or from the world, to joint i's
  parent link), the perturbed chain is ``T'[i] = T[i] O_i^-1 O_i'``: the same compiled kernels run
  on it (:func:`perturbed_arm`). Then ``[dx_w, dy_w, dz_w]`` (keys ``dx_<N+1>`` .. ``dz_<N+1>``):
  the wrist link's origin moved in the last actuated joint's child frame (the last link's length
  and offsets: ``T'[N] = T[N]`` with its translation moved); its rotations cannot move the wrist
  point, so there are none.

:func:`joint_origins` reads each actuated joint's ``<origin>`` from the URDF text, and
:func:`corrected_urdf_text` writes the origins back (nothing else changed), for the corrected model.
"""
from __future__ import annotations

import copy
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import replace
from functools import lru_cache

import numpy as np

from ..errors import ErrplanError
from ..jit import njit
from .urdf.chain import _solve


def split_geometry(joint_geometry, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``joint_geometry`` (6n + 3,) as the joints' (n, 6) and the wrist's (3,); 6n values are the
    joints' alone (the wrist unmoved)."""
    g = np.asarray(joint_geometry, float).ravel()
    if g.size == 6 * n:
        g = np.concatenate([g, np.zeros(3)])  # the joints' only: the wrist link's origin unmoved
    if g.size != 6 * n + 3:
        raise ErrplanError(f"joint_geometry: {g.size} values for {n} actuated joints: expected {6 * n + 3} "
                           f"(six per joint, then the wrist link's dx, dy, dz)")
    return g[:6 * n].reshape(n, 6), g[6 * n:]
#: Newton steps refining the inverse kinematics of a perturbed URDF arm from the declared arm's solution
IK_NEWTON_ITERS = 20


def rotation_vector_matrix(r) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``r`` (3,) (Rodrigues)."""
    r = np.asarray(r, float)
    th = float(np.linalg.norm(r))
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if th < 1e-12:
        return np.eye(3) + K
    K = K / th
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


def rotation_matrix_vector(R) -> np.ndarray:
    """Rotation vector (3,) of a rotation matrix (the inverse of :func:`rotation_vector_matrix`, angles < pi)."""
    R = np.asarray(R, float)
    c = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    th = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-9:
        return w / 2.0
    return w * th / (2.0 * math.sin(th))


def rpy_to_matrix(rpy) -> np.ndarray:
    """URDF convention: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def matrix_to_rpy(R) -> np.ndarray:
    """URDF roll, pitch, yaw of a rotation matrix (inverse of :func:`rpy_to_matrix` away from pitch ±pi/2)."""
    R = np.asarray(R, float)
    pitch = math.atan2(-R[2, 0], math.hypot(R[0, 0], R[1, 0]))
    roll = math.atan2(R[2, 1], R[2, 2])
    yaw = math.atan2(R[1, 0], R[0, 0])
    return np.array([roll, pitch, yaw])


def _numbers(text: str | None, where: str) -> np.ndarray:
    if text is None:
        return np.zeros(3)
    try:
        v = np.array([float(x) for x in text.split()], float)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ErrplanError(f"{where}: expected three finite numbers, got {text!r}")
    return v


def joint_origins(urdf_text: str, joint_names, where: str = "URDF") -> np.ndarray:
    """Each named joint's ``<origin>`` (n, 4, 4) in its parent link's frame (identity when absent)."""
    root = ET.fromstring(urdf_text)
    # the robot's own joints only: a <transmission> names its joint with a <joint> element too (no
    # origin), as example-robot-data's UR5 does
    joints = {j.get("name"): j for j in root.findall("joint")}
    out = np.empty((len(joint_names), 4, 4))
    for k, name in enumerate(joint_names):
        j = joints.get(name)
        if j is None:
            raise ErrplanError(f"{where}: no joint named {name!r}")
        o = j.find("origin")
        xyz = _numbers(None if o is None else o.get("xyz"), f"{where}: joint {name} origin xyz")
        rpy = _numbers(None if o is None else o.get("rpy"), f"{where}: joint {name} origin rpy")
        out[k] = np.eye(4)
        out[k, :3, :3] = rpy_to_matrix(rpy)
        out[k, :3, 3] = xyz
    return out


@lru_cache(maxsize=8)
def _origins(urdf_text: str, joint_names: tuple, where: str) -> np.ndarray:
    out = joint_origins(urdf_text, joint_names, where)
    out.setflags(write=False)
    return out


def perturbed_origin(O: np.ndarray, g) -> np.ndarray:
    """``O`` (4, 4) moved by ``g[:3]`` and turned by the rotation vector ``g[3:]``, both in the parent frame."""
    g = np.asarray(g, float)
    out = np.array(O, float)
    out[:3, :3] = rotation_vector_matrix(g[3:]) @ O[:3, :3]
    out[:3, 3] = O[:3, 3] + g[:3]
    return out


def perturbed_arm(arm, link_length=None, joint_geometry=None):
    """The arm with its geometry changed: planar ``link_length`` [dl1, dl2] (m); URDF
    ``joint_geometry`` (6n + 3,) in the order of :func:`errplan.scenario.joint_geometry_keys`. The arm itself when
    nothing changes."""
    from .arm import Arm

    if isinstance(arm, Arm):
        if joint_geometry is not None and np.any(joint_geometry):
            raise ErrplanError("joint_geometry is an effect of URDF arms; the planar arm has link_length")
        if link_length is None or not np.any(link_length):
            return arm
        dl = np.asarray(link_length, float)
        out = replace(arm, l1=arm.l1 + float(dl[0]), l2=arm.l2 + float(dl[1]))
        if out.l1 <= 0 or out.l2 <= 0:
            raise ErrplanError(f"link_length {dl.tolist()}: the links would be {out.l1:.4g} and {out.l2:.4g} m long")
        return out
    if link_length is not None and np.any(link_length):
        raise ErrplanError("link_length is an effect of the planar arm; a URDF arm has joint_geometry")
    if joint_geometry is None or not np.any(joint_geometry):
        return arm
    return GeometryArm(arm, joint_geometry)


class GeometryArm:
    """A URDF arm (:class:`~errplan.kinematics.urdf.UrdfArm`) whose actuated joints' origins are
    perturbed, and its wrist link's origin (module docstring). Forward kinematics and Jacobians run the compiled chain kernels on
    the perturbed chain; the inverse starts from the declared arm's solution and refines it by
    Newton steps on the perturbed chain; everything else (limits, gravity, meshes) is the declared
    arm's."""

    def __init__(self, arm, joint_geometry):
        from .urdf.model import ChainData, chain_screws

        g, gw = split_geometry(joint_geometry, arm.n)
        self._arm = arm
        self.declared_arm = arm
        self.joint_geometry = g
        self.wrist_geometry = gw
        core = arm
        while not hasattr(type(core), "forward") or hasattr(core, "_arm") and type(core).__name__ != "UrdfArm":
            core = core._arm  # a wrapper (the calibration's gravity cache): the URDF arm under it
        O = _origins(arm.urdf_text, tuple(arm.joint_names), str(arm.urdf_path))
        ch = arm.chain
        T = np.array(ch.T, float)
        for i in range(arm.n):
            T[i] = T[i] @ np.linalg.solve(O[i], perturbed_origin(O[i], g[i]))
        T[arm.n, :3, 3] += gw
        T = np.ascontiguousarray(T)
        self.chain = ChainData(T, ch.axis, ch.jtype, ch.A, ch.lo, ch.hi, chain_screws(T, ch.axis))
        self._shadow = copy.copy(core)
        self._shadow.chain = self.chain
        self._shadow.reach_map = arm.reach_map  # seeds of the declared arm's map (Newton refines below)

    def __getattr__(self, name):
        if name.startswith("__") or name == "_arm":
            raise AttributeError(name)
        return getattr(self._arm, name)

    def forward(self, q) -> np.ndarray:
        return self._shadow.forward(q)

    def jacobian(self, q) -> np.ndarray:
        return self._shadow.jacobian(q)

    def chain_points(self, q) -> np.ndarray:
        return self._shadow.chain_points(q)

    def inverse(self, w, near=None):
        w = np.asarray(w, float)
        q, ok = self._arm.inverse(w, near)
        if self.n == 3 and w.shape[-1:] == (3,):
            # compiled: the chain's projected Gauss-Newton from the declared arm's solution (its branch)
            from ..jit import kernel_array

            W = kernel_array(w.reshape(-1, 3))
            Q0 = kernel_array(np.where(ok[..., None], q, 0.0).reshape(-1, 3))
            Q = np.empty_like(Q0)
            okr = np.empty(len(W), np.bool_)
            _refine_many(self.chain, W, Q0, kernel_array(np.asarray(ok, np.bool_).reshape(-1)), Q, okr)
            q = Q.reshape(q.shape)
            ok = okr.reshape(ok.shape) & np.all(np.abs(self.forward(q) - w) < 1e-9, axis=-1) & self._arm.within_limits(q)
            return np.where(ok[..., None], q, np.nan), ok
        for _ in range(IK_NEWTON_ITERS):
            f = self.forward(q) - w
            if np.all(~ok | np.all(np.abs(f) < 1e-13, axis=-1)):
                break
            J = self.jacobian(q)
            with np.errstate(invalid="ignore"):
                step = np.linalg.solve(np.where(ok[..., None, None], J, np.eye(3)), np.where(ok[..., None], f, 0.0)[..., None])[..., 0]
            q = q - step
        ok = ok & np.all(np.abs(self.forward(q) - w) < 1e-9, axis=-1) & self._arm.within_limits(q)
        return np.where(ok[..., None], q, np.nan), ok


@njit(cache=True)
def _refine_many(chain, W, Q0, ok0, Q, ok):
    """The perturbed chain's inverse from the declared arm's solutions ``Q0`` (n, 3) where ``ok0``: the
    chain's projected Gauss-Newton (:func:`errplan.kinematics.urdf.chain._solve`, within every limit row)
    from each, into ``Q``, ``ok`` (no other seed: the declared solution's branch or none)."""
    for k in range(W.shape[0]):
        ok[k] = False
        Q[k, 0], Q[k, 1], Q[k, 2] = Q0[k, 0], Q0[k, 1], Q0[k, 2]
        if ok0[k]:
            good, a, b, c = _solve(chain, W[k, 0], W[k, 1], W[k, 2], Q0[k, 0], Q0[k, 1], Q0[k, 2], 60)
            if good:
                Q[k, 0], Q[k, 1], Q[k, 2] = a, b, c
                ok[k] = True


def wrist_joint(urdf_text: str, joint_names, wrist: str, where: str = "URDF") -> str | None:
    """The joint whose ``<origin>`` carries the wrist link's offset from the last actuated joint's child
    link: the first joint on the path from that link down to ``wrist`` (None when the wrist is that link)."""
    root = ET.fromstring(urdf_text)
    joints = [j for j in root.findall("joint") if j.get("type")]
    by_child = {j.find("child").get("link"): j for j in joints if j.find("child") is not None}
    last = next((j for j in joints if j.get("name") == joint_names[-1]), None)
    if last is None:
        raise ErrplanError(f"{where}: no joint named {joint_names[-1]!r}")
    top = last.find("child").get("link")
    link, first = wrist, None
    while link != top:
        j = by_child.get(link)
        if j is None:
            raise ErrplanError(f"{where}: the wrist link {wrist!r} is not below joint {joint_names[-1]!r}")
        first = j
        link = j.find("parent").get("link")
    return None if first is None else first.get("name")


def _replace_origin(text: str, name: str, attrs: dict, where: str) -> str:
    """``text`` with the ``<origin>`` of joint ``name`` given the attribute values ``attrs``
    (``{"xyz": "...", "rpy": "..."}``); every other character of the text, the origin's other attributes
    included, stays as it was (an origin the joint lacks is added)."""
    # the joint element: from <joint ... name="NAME" ...> to its </joint>; not a <transmission>'s
    # reference to it (that one has no type)
    m = next((mm for mm in re.finditer(r'<joint\b[^>]*\bname\s*=\s*["\']' + re.escape(name) + r'["\'][^>]*>', text)
              if re.search(r'\btype\s*=', mm.group(0))), None)
    if m is None:
        raise ErrplanError(f"{where}: no joint named {name!r}")
    end = text.find("</joint>", m.end())
    body = text[m.end():end]
    o = re.search(r"<origin\b[^>]*?/?>", body)
    if o is None:
        body = "\n    <origin " + " ".join(f'{k}="{v}"' for k, v in attrs.items()) + "/>" + body
    else:
        tag = o.group(0)
        for k, v in attrs.items():
            a = re.search(r'\b' + k + r'\s*=\s*(["\'])(.*?)\1', tag, flags=re.S)
            if a is not None:
                tag = tag[:a.start(2)] + v + tag[a.end(2):]
            else:
                close = len(tag) - (2 if tag.endswith("/>") else 1)
                tag = tag[:close].rstrip() + f' {k}="{v}"' + tag[close:]
        body = body[:o.start()] + tag + body[o.end():]
    return text[:m.end()] + body + text[end:]


def _xyz_text(v) -> str:
    return " ".join(f"{x:.12g}" for x in v)


def corrected_urdf_text(urdf_text: str, joint_names, joint_geometry, where: str = "URDF",
                        wrist: str | None = None, source_dir=None, target_dir=None) -> str:
    """The URDF text with each actuated joint's ``<origin>`` replaced by the perturbed one (xyz and
    rpy written with 12 significant digits) and the wrist link's offset added to the origin of the
    first joint from the last actuated joint's child link to ``wrist`` (:func:`wrist_joint`);
    nothing else in the text changes: a joint the fit left alone keeps its origin's text, and a joint
    only moved (or only turned) keeps its ``rpy`` (or ``xyz``) as written.

    ``source_dir`` / ``target_dir``: the folder of the URDF read and of the one written; when they
    differ, every relative mesh path is rewritten to resolve from ``target_dir``
    (:func:`relocated_mesh_paths`; ``package://`` and absolute paths kept)."""
    g, gw = split_geometry(joint_geometry, len(joint_names))
    text = urdf_text
    if np.any(gw):
        wj = wrist_joint(urdf_text, joint_names, wrist, where) if wrist is not None else None
        if wj is None:
            raise ErrplanError(f"{where}: joint_geometry moves the wrist link {wrist!r} in joint "
                               f"{joint_names[-1]!r}'s child frame, but no joint lies between them to carry it "
                               f"(add a fixed joint to the wrist link)")
        Ow = joint_origins(urdf_text, [wj], where)[0]
        text = _replace_origin(text, wj, {"xyz": _xyz_text(Ow[:3, 3] + gw)}, where)
    O = joint_origins(urdf_text, joint_names, where)
    for name, Oi, gi in zip(joint_names, O, g):
        attrs = {}
        On = perturbed_origin(Oi, gi)
        if np.any(gi[:3]):
            attrs["xyz"] = _xyz_text(On[:3, 3])
        if np.any(gi[3:]):
            attrs["rpy"] = _xyz_text(matrix_to_rpy(On[:3, :3]))
        if attrs:
            text = _replace_origin(text, name, attrs, where)
    if source_dir is not None and target_dir is not None:
        text = relocated_mesh_paths(text, source_dir, target_dir)
    return text


def relocated_mesh_paths(urdf_text: str, source_dir, target_dir) -> str:
    """The URDF text with every relative ``filename`` of a ``<mesh>`` (a path relative to the URDF's
    folder ``source_dir``) rewritten relative to ``target_dir``, so that a copy written there finds
    the same files; ``package://`` and other URIs, and absolute paths, are kept. Nothing else changes."""
    import os
    from pathlib import Path

    src = Path(source_dir).resolve()
    dst = Path(target_dir).resolve()
    if src == dst:
        return urdf_text

    def one(m):
        val = m.group(3)
        if "://" in val or os.path.isabs(val) or not val.strip():
            return m.group(0)
        try:
            new = os.path.relpath(os.path.normpath(src / val), dst)
        except ValueError:  # another drive: an absolute path
            new = str(os.path.normpath(src / val))
        new = new.replace(os.sep, "/")
        return m.group(1) + m.group(2) + new + m.group(2)

    def mesh(m):
        return re.sub(r'(\bfilename\s*=\s*)(["\'])(.*?)\2', one, m.group(0), flags=re.S)

    return re.sub(r"<mesh\b[^>]*>", mesh, urdf_text)
