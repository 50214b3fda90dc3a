"""Bounded error sets: a box of error parameters around the port estimate (docs/physics.md)."""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np


# ----------------------------------------------------------------------------- error set
@dataclass(frozen=True)
class ErrorSet:
    """A box of error parameters ``theta`` and the controller's noise bounds.

    Planar (``len(base_port) == 2``): ``theta = (dy, dz, t)``, ``port = base_port + [dy, dz]``, ``t``
    the signed lateral tip load over EI (1/m^2) in the shaft frame. Spatial (``len(base_port) ==
    3``): ``theta = (dx, dy, dz, tau, psi)``, ``port = base_port + [dx, dy, dz]``, ``tau`` the
    lateral load magnitude and ``psi`` its direction around the port->tip line (periodic on
    [0, 2 pi), sampled at ``max(8, samples)`` directions, active whenever ``tau`` can be > 0).
    ``noise = (position, angle)`` bounds each measured coordinate of P2's flexion controller.
    """

    base_port: tuple[float, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    noise: tuple[float, float] = (0.0, 0.0)
    samples: int = 5

    @classmethod
    def from_tables(cls, port, uncertainty, dim: int) -> "ErrorSet":
        """The box of a scenario's ``[port]`` and ``[uncertainty]`` tables in ``dim`` dimensions (the
        builder of :mod:`errplan.models` makes it once per arm: ``ArmModel.errors``)."""
        u, d = uncertainty, dim
        names = ("port_x", "port_y", "port_z")[3 - d:]
        boxes = [getattr(u, n) for n in names]
        if all(b is None for b in boxes):
            base, offs = port.position, [(0.0, 0.0)] * d
        else:
            base, offs = port.estimate, [b or (0.0, 0.0) for b in boxes]
        tl = u.tip_force_over_ei or (0.0, 0.0)
        noise = (u.sensor_noise.position, u.sensor_noise.angle) if u.sensor_noise else (0.0, 0.0)
        lo = [o[0] for o in offs] + [tl[0]]
        hi = [o[1] for o in offs] + [tl[1]]
        if d == 3:
            lo.append(0.0)
            hi.append(2 * math.pi if tl[1] > 0 else 0.0)
        return cls(tuple(base), tuple(lo), tuple(hi), noise, u.samples)

    @property
    def dim(self) -> int:
        return len(self.base_port)

    @property
    def lo_arr(self) -> np.ndarray:
        return np.asarray(self.lo, float)

    @property
    def hi_arr(self) -> np.ndarray:
        return np.asarray(self.hi, float)

    @property
    def active(self) -> np.ndarray:
        """Mask of the uncertain axes (those with a non-degenerate range)."""
        return self.hi_arr > self.lo_arr

    @property
    def periodic(self) -> np.ndarray:
        """Mask of the periodic axes (the load direction ``psi`` in 3-D)."""
        out = np.zeros(len(self.lo), bool)
        if self.dim == 3:
            out[4] = True
        return out

    def counts(self, samples: int | None = None) -> np.ndarray:
        """Samples per axis: ``samples`` on an uncertain axis, ``max(8, samples)`` on a periodic one."""
        n = samples or self.samples
        c = np.where(self.active, n, 1)
        return np.where(self.active & self.periodic, max(8, n), c).astype(np.int64)

    def axis_samples(self, samples: int | None = None) -> list[np.ndarray]:
        out = []
        for l, h, c, per in zip(self.lo, self.hi, self.counts(samples), self.periodic):
            if c == 1:
                out.append(np.array([l]))
            elif per:
                out.append(l + (h - l) * np.arange(c) / c)
            else:
                out.append(np.linspace(l, h, c))
        return out

    def sample_grid(self, samples: int | None = None) -> np.ndarray:
        """Parameters (m, na) on a regular grid over the box (C order over the axes)."""
        axes = self.axis_samples(samples)
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(self.lo))

    def corners(self) -> np.ndarray:
        axes = [(l, h) if h > l and not per else (l,) for l, h, per in zip(self.lo, self.hi, self.periodic)]
        return np.array(list(itertools.product(*axes)), float)

    def port_corners(self) -> np.ndarray:
        """True ports (c, d) at the corners of the port box."""
        d = self.dim
        axes = [(l, h) if h > l else (l,) for l, h in zip(self.lo[:d], self.hi[:d])]
        return np.asarray(self.base_port, float) + np.array(list(itertools.product(*axes)), float)

    def spacing(self, samples: int | None = None) -> np.ndarray:
        c = self.counts(samples)
        span = self.hi_arr - self.lo_arr
        return np.where(self.periodic, span / c, span / np.maximum(c - 1, 1))

    def port(self, theta: np.ndarray) -> np.ndarray:
        return np.asarray(self.base_port) + theta[..., :self.dim]

    def noise_corners(self) -> np.ndarray:
        """Sensor-noise vectors at the corners of the noise set.

        Planar (c, 6): ``[pw(2), pt(2), th_w, th_t]`` at the corners of the box. Spatial (c, 7):
        ``[delta(3), tilt_w(2), tilt_t(2)]`` (see :func:`spatial_noise_corners`).
        """
        pos, ang = self.noise
        if self.dim == 3:
            return spatial_noise_corners(pos, ang)
        if pos == 0 and ang == 0:
            return np.zeros((1, 6))
        axes = [(-pos, pos) if pos > 0 else (0.0,)] * 4 + [(-ang, ang) if ang > 0 else (0.0,)] * 2
        return np.array(list(itertools.product(*axes)), float)


def spatial_noise_corners(position: float, angle: float, azimuths: int = 4,
                          in_plane: bool = False) -> np.ndarray:
    """Noise vectors (c, 7) of the 3-D flexion controller's sensor-noise set at its corners.

    The controller's ``Jhat`` depends on the measured positions only through the chord ``pt - pw``
    (the estimated port moves with the wrist), so the two position boxes enter through their
    difference ``delta`` in ``[-2 position, 2 position]^3``, taken at ``{-2p, 0, 2p}`` per axis (the
    set of chords the corners of the two boxes give; in the plane the planar controller's 64
    corners give the same Jacobians; the middle values matter: an out-of-plane chord tilt lowers the
    worst case, so the worst often sits at an edge's middle, not a corner). Each end direction
    is tilted by the full ``angle`` toward ``azimuths`` directions evenly around its cone,
    ``tilt = angle (cos a, sin a)`` in the end's frame ``(e1, e2)`` (``e1`` in the true bending
    plane, ``e2`` its normal): a cone has no corners, so the worst case over these is a lower bound
    of the worst case over the set. ``in_plane``: only the noise of the bending plane (``delta``
    along ``y, z`` and tilts ``+-angle e1``), the planar controller's set.
    """
    pos, ang = float(position), float(angle)
    dvals = (-2 * pos, 0.0, 2 * pos) if pos > 0 else (0.0,)
    dx = (0.0,) if in_plane else dvals
    if ang > 0:
        az = (0.0, math.pi) if in_plane else tuple(2 * math.pi * i / azimuths for i in range(azimuths))
        tilts = [(ang * math.cos(a), 0.0 if in_plane else ang * math.sin(a)) for a in az]
    else:
        tilts = [(0.0, 0.0)]
    rows = [(a, b, c, *tw, *tt) for a in dx for b in dvals for c in dvals for tw in tilts for tt in tilts]
    return np.array(rows, float)


# The effects that change the true Jacobian at a tip, or the frame the loop closes in (planar Plant
# keyword arguments; the others move the measurement only). ``tracker_rotation``: the rotation of a
# ``tracker_registration`` (the controller closes the loop on ``R x + b``: ``G = I - k R J Jhat^-1``).
JACOBIAN_EFFECTS = ("port_offset", "joint_offset", "gravity_sag", "world_load", "link_length", "instrument_length",
                    "tracker_rotation")
#: the spatial [effects] tables that change the true Jacobian or the loop's frame (``port_offset`` folded
#: into the error set's base port); ``tracker_offset`` (a constant b) changes neither
SPATIAL_JACOBIAN_EFFECTS = ("joint_offset", "gravity_sag", "shaft_flexion", "joint_geometry", "instrument_length",
                            "tracker_registration")
#: every effect the metrics express: the fields and the gain certificates take them into J, Jhat or R;
#: an effect outside this list (history- or motion-dependent: backlash, port_friction, a tracker latency,
#: or any effect added later) is simulated but not certified (:func:`uncovered_effects`)
EXPRESSIBLE_EFFECTS = ("port_offset", "joint_offset", "gravity_sag", "shaft_flexion", "tracker_offset",
                       "link_length", "joint_geometry", "instrument_length", "tracker_registration")


def _nonzero(params) -> bool:
    """True when an effect table has some parameter that is not zero (a zero effect is no effect)."""
    for v in dict(params).values():
        try:
            if float(v) != 0.0:
                return True
        except (TypeError, ValueError):
            return True
    return False


def uncovered_effects(sc) -> list[str]:
    """The sorted names of the scenario truth's ``[effects]`` that the metrics cannot express (every
    effect but those of :data:`EXPRESSIBLE_EFFECTS`; an effect whose parameters are all zero is none):
    the fields and gain certificates hold for the truth without them, the simulation has them. A plan
    on such a scenario says its certificate does not cover them (docs/physics.md "From measured data
    to the plan")."""
    return sorted(name for name, p in (getattr(sc, "effects", None) or {}).items()
                  if name not in EXPRESSIBLE_EFFECTS and _nonzero(p))


def error_set(sc, es: ErrorSet | None = None) -> tuple[ErrorSet, dict]:
    """The scenario's error set (``es``, default from its tables) with a ``port_offset`` effect folded
    into the true port, and the remaining effects that change the true Jacobian or the loop's frame
    (planar: Plant keyword arguments; spatial: the effect tables). An empty mapping: a truth the
    compiled kernels cover. An :class:`errplan.models.ArmModel` answers with what it was built with."""
    from dataclasses import replace

    from .kinematics.truth import effect_kwargs

    if es is None and hasattr(type(sc), "true_errors"):  # an ArmModel: built once
        return sc.true_errors, dict(sc.jacobian_effects)
    es = es or ErrorSet.from_tables(sc.port, sc.uncertainty, sc.dim)
    if sc.dim == 2:
        allkw = effect_kwargs(sc.effects)
        kw = {k: v for k, v in allkw.items() if k in JACOBIAN_EFFECTS and any(x != 0 for x in v)}
        if "tracker_rotation" in kw and "tracker_offset" in allkw:  # the loop's frame: R x + b, b with it
            kw["tracker_offset"] = allkw["tracker_offset"]
        off = kw.pop("port_offset", None)
    else:
        kw = {name: p for name, p in sc.effects.items()
              if name in SPATIAL_JACOBIAN_EFFECTS and any(v != 0 for k, v in p.items()
                                                          if name != "tracker_registration" or k[0] == "r")}
        po = sc.effects.get("port_offset")
        off = tuple(po[a] for a in ("dx", "dy", "dz")) if po else None
    if off is not None:
        es = replace(es, base_port=tuple(b + o for b, o in zip(es.base_port, off)))
    return es, kw
