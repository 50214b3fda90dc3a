"""The candidate effects of docs/physics.md ("Effects a real bench shows"), one small class each.

Every effect has the same interface (PySINDy's feature-library style):

- class attributes ``name`` (the physics.md name), ``params`` (parameter names), ``units`` and
  ``default_scales`` (a typical size of each parameter, SI: it sets the finite-difference step and
  the units the fit works in, and the "size" used by the identifiability check);
- ``apply(plant, values)``: the :class:`errplan.simulation.Plant` with the effect *added* to what
  the plant already has (every effect is additive in its parameters, so a declared effect plus a
  fitted correction is again that effect);
- ``fit(data, base)``: fit this effect alone to measured data (nonlinear least squares on the pose
  residual, see :class:`EffectModel`); settings live in ``__init__``, fitted values end with an
  underscore (``values_``, ``sigma_``, ...), ``fit`` returns ``self``.

:class:`EffectModel` is a combination of effects (the empty combination is the declared model)
and does the fitting: ``tracked tip = plant(values).tip(q_enc, u) + tracker offset``, residual
``tracked - model`` over all rows at once, ``scipy.optimize.least_squares`` in scaled units
(value / default scale) with a central-difference Jacobian, covariance ``s^2 (J^T J)^-1`` with
``s^2 = RSS / (2n - p)``, and an identifiability check on the column-normalised Jacobian
(condition number and the largest correlation between parameter estimates).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .errors import ErrplanError

#: an effect combination whose normalised Jacobian is worse conditioned than this, or whose
#: parameter estimates correlate more than MAX_CORRELATION, cannot be identified from the data.
MAX_CONDITION = 1.0e3
MAX_CORRELATION = 0.995


class Effect:
    """Base class: one effect of docs/physics.md with a fixed parametrisation."""

    name: str = ""
    params: tuple[str, ...] = ()
    units: tuple[str, ...] = ()
    default_scales: tuple[float, ...] = ()
    plant_field: str = ""
    description: str = ""
    #: identifiable parameters chosen by QR with column pivoting before the fit (geometric groups)
    qr_identify: bool = False

    def __init__(self, scales: Sequence[float] | None = None, *, dim: int = 2, n_joints: int = 2,
                 fixed: Sequence[bool] | None = None):
        self.dim, self.n_joints = int(dim), int(n_joints)
        if self.dim != 2:  # the spatial parametrisation (docs/physics.md "Effects in 3-D")
            from .scenario import effect_params

            self.params = effect_params(self.name, self.dim, self.n_joints)
            self.units, self.default_scales = self.spatial_units_scales()
        self.scales = tuple(float(s) for s in (scales if scales is not None else self.default_scales))
        if len(self.scales) != len(self.params) or not all(s > 0 for s in self.scales):
            raise ErrplanError(f"{self.name}: scales {list(self.scales)}: expected {len(self.params)} numbers > 0")
        #: parameters whose sensitivity is identically zero for this robot (held at 0, never fitted,
        #: reported as not identifiable: a vertical axis's gravity sag)
        self.fixed = tuple(bool(f) for f in (fixed if fixed is not None else (False,) * len(self.params)))
        if len(self.fixed) != len(self.params):
            raise ErrplanError(f"{self.name}: fixed {list(self.fixed)}: expected {len(self.params)} flags")
        self.why_fixed = ""

    def spatial_units_scales(self) -> tuple[tuple[str, ...], tuple[float, ...]]:
        """Units and typical sizes of the spatial parameters (the planar ones, per axis)."""
        n = len(self.params)
        return (self.units[0],) * n, (self.default_scales[0],) * n

    def __repr__(self) -> str:
        return f"{type(self).__name__}()" if self.dim == 2 else f"{type(self).__name__}(dim={self.dim}, n_joints={self.n_joints})"

    @property
    def n_params(self) -> int:
        return len(self.params)

    def apply(self, plant, values: Sequence[float]):
        """The plant with this effect added (``values`` in physics.md units, order ``params``)."""
        cur = np.asarray(getattr(plant, self.plant_field), float)
        add = np.asarray(values, float)
        if cur.shape != add.shape:
            raise ErrplanError(f"{self.name}: {len(add)} values {add.tolist()} for a plant with {cur.size} "
                               f"({self.plant_field} = {cur.tolist()})")
        return plant.with_(**{self.plant_field: tuple(float(v) for v in cur + add)})

    def values_of(self, plant) -> np.ndarray:
        """The values this effect has in a plant."""
        return np.asarray(getattr(plant, self.plant_field), float)

    def as_dict(self, values: Sequence[float]) -> dict[str, float]:
        return {p: float(v) for p, v in zip(self.params, values)}

    def fit(self, q: np.ndarray, u: np.ndarray, tracked: np.ndarray, base) -> "Effect":
        """Fit this effect alone (see :meth:`EffectModel.fit`); sets ``values_``, ``sigma_``,
        ``model_`` (the fitted :class:`EffectModel`). Returns self."""
        m = EffectModel([self]).fit(q, u, tracked, base)
        self.model_ = m
        self.values_ = m.values_
        self.sigma_ = m.sigma_
        return self


def _declare(cls_name: str, name: str, params: tuple[str, ...], units: str, scale: float, plant_field: str,
             description: str, **methods) -> type[Effect]:
    """One catalogue entry of physics.md's table as an :class:`Effect` subclass (every parameter in the
    same unit and default scale)."""
    return type(cls_name, (Effect,), {"name": name, "params": params, "units": (units,) * len(params),
                                      "default_scales": (scale,) * len(params), "plant_field": plant_field,
                                      "description": description, "__module__": __name__,
                                      "__doc__": f"``{name}``: {description}.", **methods})


def _gravity_spatial_units_scales(self):
    # c_i in rad per N m: scaled so that one unit is about 1 mrad of sag (set per arm by
    # :func:`catalogue` from the arm's generalized gravity)
    return ("rad/(N m)",) * len(self.params), (1e-2,) * len(self.params)


def _friction_spatial_units_scales(self):
    return tuple(self.units), tuple(self.default_scales)  # fa, fn in 3-D too


PortOffset = _declare("PortOffset", "port_offset", ("dy", "dz"), "m", 1e-3, "port_offset",
                      "the true port is the declared port + [dy, dz]")
JointOffset = _declare("JointOffset", "joint_offset", ("dq1", "dq2"), "rad", 1e-3, "joint_offset",
                       "link angles = encoder angles + [dq1, dq2]")
TrackerOffset = _declare("TrackerOffset", "tracker_offset", ("by", "bz"), "m", 1e-3, "tracker_offset",
                         "tracked tip = true tip + [by, bz]")
GravitySag = _declare("GravitySag", "gravity_sag", ("c1", "c2", "c3"), "rad", 1e-3, "gravity_sag",
                      "link angles = encoder angles - [c1 cos a1 + c2 cos a2, c3 cos a2]",
                      spatial_units_scales=_gravity_spatial_units_scales)
ShaftFlexion = _declare("ShaftFlexion", "shaft_flexion", ("fy", "fz"), "1/m^2", 1.0, "world_load",
                        "a constant world-frame tip load over EI bends the shaft (P2 beam)")
PortFriction = _declare("PortFriction", "port_friction", ("fa", "fn"), "m", 1e-3, "friction",
                        "the port holds the tip back against the motion the last command produced under the "
                        "declared model (axial fa, normal fn)",
                        spatial_units_scales=_friction_spatial_units_scales)


#: tracker_latency's largest tau, in steps of the data (docs/physics.md: 0 <= tau <= 5 steps)
MAX_LATENCY_STEPS = 5.0

#: a radian of a geometric parameter counts like a metre at this lever (physics.md: identifiability on
#: columns with metres and radians weighted by a 0.1 m lever): radians are scaled by 1e-2 where metres
#: are scaled by 1e-3
GEOMETRY_LEVER = 0.1
#: the QR identifiability threshold: a parameter is identifiable when |R_ii| >= QR_RTOL |R_11|
QR_RTOL = 1e-6


class _Geometric(Effect):
    """A geometric group (physics.md "Closing the loop when the catalogue lacks the effect"): fitted
    like any effect, but its identifiable parameters are chosen first by QR with column pivoting on
    the fit rows' regressor (:meth:`EffectModel.fit`), the others held at zero and named."""

    qr_identify = True
    #: whether the fit keeps only the identifiable parameters the rows need (forward selection,
    #: :meth:`EffectModel.identify`): for a group of many parameters of which a real error is a few
    sparse = False
    #: plant fields of the parameters, in order: (field, number of parameters)
    fields: tuple[tuple[str, int], ...] = ()

    def _fields(self):
        return self.fields or ((self.plant_field, self.n_params),)

    def apply(self, plant, values):
        add = np.asarray(values, float)
        if add.shape != (self.n_params,):
            raise ErrplanError(f"{self.name}: {add.size} values {add.tolist()}: expected {self.n_params}")
        changes, i = {}, 0
        for fld, k in self._fields():
            cur = np.asarray(changes.get(fld, getattr(plant, fld)), float)
            if cur.shape != (k,):
                raise ErrplanError(f"{self.name}: a plant with {fld} = {cur.tolist()} cannot take {k} values")
            changes[fld] = tuple(float(v) for v in cur + add[i:i + k])
            i += k
        return plant.with_(**changes)

    def values_of(self, plant) -> np.ndarray:
        return np.concatenate([np.asarray(getattr(plant, fld), float) for fld, _ in self._fields()])


def _units_scales(units: Sequence[str]) -> tuple[tuple[str, ...], tuple[float, ...]]:
    return tuple(units), tuple(1e-3 if u == "m" else 1e-3 / GEOMETRY_LEVER for u in units)


class LinkLength(_Geometric):
    """``link_length`` (planar): link lengths = declared + [dl1, dl2]."""

    name, params, units, default_scales = "link_length", ("dl1", "dl2"), ("m", "m"), (1e-3, 1e-3)
    plant_field = "link_length"
    description = "link lengths = declared + [dl1, dl2]"

    def __init__(self, scales=None, *, dim: int = 2, n_joints: int = 2, fixed=None):
        if int(dim) != 2:
            raise ErrplanError("link_length is an effect of the planar arm; a URDF arm has joint_geometry")
        super().__init__(scales, dim=dim, n_joints=n_joints, fixed=fixed)


class InstrumentLength(_Geometric):
    """``instrument_length``: the instrument is declared length + dL."""

    name, params, units, default_scales = "instrument_length", ("dL",), ("m",), (1e-3,)
    plant_field = "instrument_length"
    description = "the instrument is declared length + dL"


class TrackerRegistration(_Geometric):
    """``tracker_registration``: tracked tip = R(r) true tip + b (planar: r = rx about the world x axis)."""

    name, params = "tracker_registration", ("rx", "by", "bz")
    units, default_scales = _units_scales(("rad", "m", "m"))
    description = "tracked tip = R(r) true tip + b, R(r) the rotation by r about the world origin"

    def spatial_units_scales(self):
        return _units_scales(("rad",) * 3 + ("m",) * 3)

    def _fields(self):
        k = 1 if self.dim == 2 else 3
        return (("tracker_rotation", k), ("tracker_offset", self.dim))


class JointGeometry(_Geometric):
    """``joint_geometry`` (URDF arms): each actuated joint's origin moved by [dx, dy, dz] and turned by
    the rotation vector [rx, ry, rz] in its parent link's frame (keys ``dx_1`` .. ``rz_N``), and the
    wrist link's origin moved by [dx, dy, dz] in the last actuated joint's child frame (keys
    ``dx_<N+1>`` .. ``dz_<N+1>``: the last link's length)."""

    name, params, units, default_scales = "joint_geometry", (), (), ()
    plant_field = "joint_geometry"
    sparse = True  # 6N + 3 parameters: a real error is a few of them
    description = ("each actuated joint's origin moved by [dx, dy, dz] and turned by [rx, ry, rz] in its parent frame; "
                   "the wrist link's origin moved by [dx, dy, dz] in the last joint's child frame")

    def __init__(self, scales=None, *, dim: int = 2, n_joints: int = 2, fixed=None):
        if int(dim) != 3:
            raise ErrplanError("joint_geometry is an effect of URDF arms; the planar arm has link_length")
        super().__init__(scales, dim=dim, n_joints=n_joints, fixed=fixed)

    def spatial_units_scales(self):
        return _units_scales(("m", "m", "m", "rad", "rad", "rad") * self.n_joints + ("m", "m", "m"))


#: plausible sizes of a bench's effects, by unit (SI): a fitted value beyond these is flagged in the
#: report (not rejected): 20 mm of offset or length error, 50 mrad of angle, a tip load over EI of
#: 5 /m^2 (P2's 1 N on the ZEUS shaft is 1.7 /m^2), and for the spatial gravity sag 20 mrad of sag at
#: the joint's RMS generalized gravity (a joint far softer than an arm's servos)
PLAUSIBLE = {"m": 0.02, "rad": 0.05, "1/m^2": 5.0}
PLAUSIBLE_SAG = 0.02


def implausible(model: "EffectModel", values=None) -> list[dict]:
    """The parameters of a fitted combination whose size is physically implausible (:data:`PLAUSIBLE`):
    ``[{"effect", "param", "value", "limit", "unit", "why"}]``."""
    values = model.values_ if values is None else np.asarray(values, float)
    out, i = [], 0
    for e in model.effects:
        for p, unit, scale, v in zip(e.params, e.units, e.scales, values[i:i + e.n_params]):
            if unit == "rad/(N m)":
                lim, size, what = PLAUSIBLE_SAG, abs(v) * 1e-3 / scale, "rad of sag at the joint's RMS gravity torque"
            else:
                lim, size, what = PLAUSIBLE.get(unit, math.inf), abs(v), unit
            if size > lim:
                out.append({"effect": e.name, "param": p, "value": float(v), "limit": lim, "unit": unit,
                            "why": f"{e.name}.{p} = {v:.4g} {unit}: {size:.3g} {what} is beyond a plausible "
                                   f"{lim:g} (a parameter absorbing an effect the combination lacks?)"})
        i += e.n_params
    return out


class Backlash(Effect):
    """``backlash``: play of half-width b_i between encoder and link, history-dependent
    (:func:`backlash_angles`; a run's first row mid-band)."""

    name, params, units, default_scales = "backlash", ("b1", "b2"), ("rad", "rad"), (1e-3, 1e-3)
    plant_field = "backlash"
    description = "play of half-width b_i between encoder and link: theta = clip(theta before, q - b, q + b)"
    #: a candidate alone, beside the geometric groups (its rows need their runs)
    history = True


class TrackerLatency(Effect):
    """``tracker_latency`` (docs/physics.md "Measured data as a bench records it"): the tracked tip
    of a row is the true tip at the row's time - tau, the true tip moving linearly in time between
    a run's rows (:func:`delayed`); ``tau`` in seconds when the rows have a ``time`` column, else in
    steps; 0 <= tau <= 5 steps. History-dependent: a row's prediction uses its run up to that row.
    A physical effect of the catalogue: fitted alone and combined with the others."""

    name, params, units, default_scales = "tracker_latency", ("tau",), ("steps",), (1.0,)
    plant_field = "tracker_latency"
    description = "the tracked tip of a row is the true tip at the row's time - tau (linear in time between rows)"
    #: the fit starts from the best of these sizes (scaled units: steps); RSS(tau) has a kink wherever
    #: a row's delayed time crosses another row's time, so a local start alone may stop on one
    starts = (0.25, 0.75, 1.25, 2.0, 3.0, 4.5)
    #: the parameter's range (scaled units: steps)
    bounds = (0.0, MAX_LATENCY_STEPS)

    def spatial_units_scales(self):
        return tuple(self.units), tuple(self.default_scales)

    def for_time(self, unit: str = "steps", step: float = 1.0) -> "TrackerLatency":
        """Set the parameter's unit for the rows' time (``"seconds"``: tau in s, one scaled unit a
        typical ``step`` of the data; ``"steps"``: tau in steps). Returns self."""
        step = float(step)
        if not (math.isfinite(step) and step > 0):
            raise ErrplanError(f"tracker_latency: the data's step {step!r}: expected a duration > 0")
        self.units = ("s",) if unit == "seconds" else ("steps",)
        self.scales = (step if unit == "seconds" else 1.0,)
        return self


#: the catalogue's physical effects, in physics.md order
CATALOGUE: tuple[type[Effect], ...] = (PortOffset, JointOffset, TrackerOffset, GravitySag, ShaftFlexion, PortFriction,
                                       TrackerLatency)

#: the geometric groups (tried after the physical effects; which apply depends on the arm)
GEOMETRY: tuple[type[Effect], ...] = (LinkLength, JointGeometry, InstrumentLength, TrackerRegistration)
EFFECTS: dict[str, type[Effect]] = {c.name: c for c in CATALOGUE + GEOMETRY + (Backlash,)}


def geometry_names(dim: int) -> list[str]:
    """The geometric groups of a planar (``dim`` 2) or URDF (3) arm."""
    return [c.name for c in GEOMETRY if c.name != ("joint_geometry" if dim == 2 else "link_length")]


#: a joint whose generalized gravity stays below this share of the largest one over the joint
#: range has an identically zero sensitivity (a vertical axis): its gravity sag is not identifiable
GRAVITY_ZERO = 1e-9


def gravity_scales(arm) -> tuple[tuple[float, ...], tuple[bool, ...], str]:
    """For a URDF arm: typical sizes of the gravity-sag parameters c_i (rad per N m, 1 mrad of sag
    at the RMS generalized gravity of joint i over a grid of its joint range), which joints have an
    identically zero generalized gravity (a vertical axis: c_i not identifiable), and a sentence
    saying so. Raises :class:`ErrplanError` for a URDF without inertial data."""
    g = [np.linspace(lo, hi, 5) for lo, hi in arm.limits]
    Q = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, arm.n)
    Q = Q[arm.within_limits(Q)] if np.any(arm.within_limits(Q)) else Q
    tau = np.asarray(arm.gravity_torque(Q), float)
    rms = np.sqrt(np.mean(tau ** 2, axis=0))
    zero = rms <= GRAVITY_ZERO * max(float(rms.max()), 1e-300)
    scales = tuple(float(1e-3 / r) if not z else 1.0 for r, z in zip(rms, zero))
    names = [arm.joint_names[i] for i in np.flatnonzero(zero)]
    why = (f"the generalized gravity of joint(s) {', '.join(names)} is identically zero (a vertical axis): "
           f"its sag parameter is not identifiable") if names else ""
    return scales, tuple(bool(z) for z in zero), why


def catalogue(sc, names: Sequence[str] | None = None, *, skip_without_gravity: bool = False,
              data=None) -> list[Effect]:
    """The catalogue's effects (``names``, default all, in physics.md order) for scenario ``sc``:
    its dimension and, in 3-D, its arm's joints; gravity sag scaled by the arm's generalized gravity
    with identically zero joints fixed. A URDF without inertial data has no gravity sag: one clear
    error, or (``skip_without_gravity``) the catalogue without it. ``data`` (measured data) sets
    ``tracker_latency``'s unit and scale from the rows' time (seconds or steps)."""
    out = _catalogue(sc, names, skip_without_gravity)
    if data is not None:
        for e in out:
            if isinstance(e, TrackerLatency):
                e.for_time(data.time_unit, data.time_step)
    return out


def _catalogue(sc, names, skip_without_gravity) -> list[Effect]:
    names = [c.name for c in CATALOGUE] if names is None else list(names)
    if sc.dim == 2:
        return [make_effect(n) for n in names]
    from .kinematics import arm_for

    arm = arm_for(sc.robot)
    out = []
    for n in names:
        if n == "gravity_sag":
            try:
                scales, fixed, why = gravity_scales(arm)
            except ErrplanError as e:
                if skip_without_gravity:
                    continue
                raise ErrplanError(f"{sc.source}: gravity_sag needs the arm's generalized gravity: {e}") from None
            e = make_effect(n, dim=3, n_joints=arm.n, scales=scales, fixed=fixed)
            e.why_fixed = why
            out.append(e)
        else:
            out.append(make_effect(n, dim=3, n_joints=arm.n))
    return out


def latency_in_data_units(effects: dict, sc, data) -> dict:
    """A scenario's ``[effects]`` with ``tracker_latency``'s tau in the unit of measured ``data``'s
    time (the scenario's tau is in seconds with ``[sensors] step_time``, else in steps)."""
    lat = effects.get("tracker_latency")
    if not lat or data is None:
        return effects
    step = sc.sensors.step_time
    tau = float(lat.get("tau", 0.0))
    if data.time_unit == "seconds" and step is None:
        tau *= data.time_step
    elif data.time_unit == "steps" and step is not None:
        tau /= step
    return {**effects, "tracker_latency": {"tau": tau}}


def latency_in_scenario_units(effects: dict, sc, data) -> tuple[dict, float | None]:
    """``[effects.tracker_latency] tau`` of a scenario written from a calibration on ``data``: the
    scenario's tau is in seconds with ``[sensors] step_time``, else in steps, the fit's in the data's
    unit. Data in steps for a scenario with step_time: tau times step_time. Data in seconds for a
    scenario without: tau stays in seconds and the scenario gains ``step_time`` (the data's median
    step, returned; None otherwise) so that it reads so."""
    lat = effects.get("tracker_latency")
    if not lat or data is None:
        return effects, None
    step = sc.sensors.step_time
    out = dict(effects)
    if data.time_unit == "steps" and step is not None:
        out["tracker_latency"] = {"tau": float(lat["tau"]) * step}
    elif data.time_unit == "seconds" and step is None:
        return out, data.time_step
    return out, None


def make_effect(name: str, **kw) -> Effect:
    try:
        cls = EFFECTS[name]
    except KeyError:
        raise ErrplanError(f"effect {name!r}: not an effect of docs/physics.md ({', '.join(EFFECTS)})") from None
    return cls(**kw)


class _GravityCache:
    """A URDF arm whose generalized gravity is remembered for the last few joint arrays it was
    asked about (by identity): the fits evaluate the plant hundreds of times on the same rows, and
    tau_g depends only on the encoder angles. Everything else is the arm's."""

    def __init__(self, arm, size: int = 8):
        self._arm = arm
        self._memo: list = []
        self._size = size

    def __getattr__(self, name):
        if name.startswith("__") or name == "_arm":
            raise AttributeError(name)
        return getattr(self._arm, name)

    def gravity_torque(self, q):
        for ref, tau in self._memo:
            if ref is q:
                return tau
        tau = self._arm.gravity_torque(q)
        if isinstance(q, np.ndarray):
            self._memo.insert(0, (q, tau))
            del self._memo[self._size:]
        return tau


def with_gravity_cache(plant):
    """``plant`` with its URDF arm's generalized gravity memoised (a planar plant as it is)."""
    if plant.dim != 3 or isinstance(plant.arm, _GravityCache):
        return plant
    return plant.with_(arm=_GravityCache(plant.arm))


def backlash_angles(q: np.ndarray, run: np.ndarray | None, b) -> np.ndarray:
    """Link angles (n, N) behind a play of half-width ``b`` (N,) for encoder rows ``q`` (n, N) in run
    order (``run`` (n,), each run's rows contiguous, step by step): ``theta = clip(theta of the row
    before, q - b, q + b)``; at a run's first row theta = q (mid-band: the move to the start was not
    recorded). Docs/physics.md ``backlash``."""
    q = np.asarray(q, float)
    b = np.abs(np.asarray(b, float))  # a half-width: its sign means nothing
    if not np.any(b):
        return q
    if run is None:
        raise ErrplanError("backlash depends on the motion's history: the rows' runs are needed")
    run = np.asarray(run)
    first = np.ones(len(q), bool)
    first[1:] = run[1:] != run[:-1]
    start = np.maximum.accumulate(np.where(first, np.arange(len(q)), 0))
    pos = np.arange(len(q)) - start
    theta = q.copy()
    for k in range(1, int(pos.max()) + 1 if len(pos) else 0):
        idx = np.flatnonzero(pos == k)
        theta[idx] = np.clip(theta[idx - 1], q[idx] - b, q[idx] + b)
    return theta


def _run_starts(run: np.ndarray) -> np.ndarray:
    """For rows in run order (each run's rows contiguous), the index of each row's run's first row."""
    n = len(run)
    first = np.ones(n, bool)
    first[1:] = run[1:] != run[:-1]
    return np.maximum.accumulate(np.where(first, np.arange(n), 0)) if n else np.zeros(0, int)


def median_step(time: np.ndarray, run: np.ndarray) -> float:
    """The median duration between consecutive rows of a run (1.0 when there is none)."""
    same = run[1:] == run[:-1]
    dt = np.diff(np.asarray(time, float))[same]
    dt = dt[dt > 0]
    return float(np.median(dt)) if len(dt) else 1.0


def delayed(x: np.ndarray, time: np.ndarray | None, run: np.ndarray | None, tau: float) -> np.ndarray:
    """``tracker_latency`` (docs/physics.md): the value (n, d) at each row's time - ``tau`` of a quantity
    ``x`` (n, d) known at the rows, moving linearly in time between two rows of a run, and before a
    run's first row equal to the first row's. Rows in run order, each run contiguous, times strictly
    increasing within a run (``time`` None: the step index within the run). Causal for tau >= 0: a
    row uses its run up to that row."""
    x = np.asarray(x, float)
    n = len(x)
    if not tau or n == 0:
        return x
    if run is None:
        raise ErrplanError("tracker_latency depends on the motion's history: the rows' runs are needed")
    run = np.asarray(run)
    start = _run_starts(run)
    idx = np.arange(n)
    rel = (idx - start).astype(float) if time is None else np.asarray(time, float) - np.asarray(time, float)[start]
    # one increasing key over all runs: each run's relative time, shifted past the runs before it by
    # more than tau (a row's delayed time never reaches into the previous run)
    starts = np.flatnonzero(start == idx)
    ends = np.r_[starts[1:], n] - 1
    base = np.concatenate([[0.0], np.cumsum(rel[ends] + abs(tau) + 1.0)[:-1]])
    key = rel + np.repeat(base, ends - starts + 1)
    s = key - tau
    j = np.searchsorted(key, s, side="right") - 1
    before = j < start
    j = np.maximum(j, start)
    nxt = np.minimum(j + 1, n - 1)
    inside = ~before & (nxt > j) & (nxt <= idx)
    w = np.where(inside, (s - key[j]) / np.where(inside, key[nxt] - key[j], 1.0), 0.0)
    w = np.clip(w, 0.0, 1.0)
    step = np.where((w > 0)[:, None], w[:, None] * (x[nxt] - x[j]), 0.0)
    return x[j] + step


def latency_of(plant, time: np.ndarray | None, run: np.ndarray | None) -> float:
    """The plant's ``tracker_latency`` tau within its range 0 .. 5 steps of the rows (0 without one)."""
    tau = float(np.asarray(getattr(plant, "tracker_latency", (0.0,)) or (0.0,), float)[0])
    if not tau:
        return 0.0
    step = 1.0 if time is None or run is None else median_step(time, np.asarray(run))
    return min(max(tau, 0.0), MAX_LATENCY_STEPS * step)


def predict_tracked(plant, q: np.ndarray, u: np.ndarray | None, run: np.ndarray | None = None,
                    time: np.ndarray | None = None) -> np.ndarray:
    """What the tracker reads (n, 2) for encoder angles ``q`` (n, 2) and friction's directions ``u``
    (n, 2): the unit motion the last command produced under the declared model
    (:meth:`errplan.experiment.MeasuredData.commanded_directions`). History-dependent effects
    (``backlash``, ``tracker_latency``) need the rows' ``run`` (rows in run order, steps ascending);
    ``tracker_latency`` also their ``time`` (:attr:`errplan.experiment.MeasuredData.time`). Rows left
    out of a residual (dropouts, outliers) stay in ``q`` and ``time``: their tips are the history
    (:meth:`errplan.experiment.MeasuredData.without_tips`)."""
    if any(getattr(plant, "backlash", ())):
        q = backlash_angles(q, run, plant.backlash)
    tip = plant.tip(q, u)
    tau = latency_of(plant, time, run)
    if tau:
        if time is None:  # never guess: rows left out of an array would shift a step index
            raise ErrplanError("tracker_latency depends on the rows' times: pass the data's time (MeasuredData.time)")
        tip = delayed(tip, time, run, tau)
    return plant.tracked(tip)


class EffectModel:
    """A combination of effects added to a base plant, fitted to the pose residual.

    Parameters
    ----------
    effects : sequence of :class:`Effect` (empty: the base plant alone, nothing to fit).
    fd_step : central-difference step in scaled units (value / default scale).
    max_nfev : evaluation budget of ``least_squares``.

    Fitted attributes: ``values_`` (p,) physics.md units, ``cov_`` (p, p), ``sigma_`` (p,),
    ``rss_`` (m^2), ``n_obs_`` (scalar residuals, d per row), ``condition_`` (of the
    column-normalised Jacobian), ``correlation_`` (of the free parameters), ``max_correlation_``,
    ``identifiable_`` (bool), ``why_`` (a sentence when not identifiable), ``success_``.
    Parameters an effect holds fixed for the robot (:attr:`Effect.fixed`: identically zero
    sensitivity) are not fitted: value 0, sigma and covariance NaN.
    """

    def __init__(self, effects: Sequence[Effect] = (), *, fd_step: float = 1e-3, max_nfev: int = 200,
                 hold: Sequence[bool] | None = None, drop: Sequence[bool] | None = None):
        self.effects = list(effects)
        #: parameters held at zero because QR found them not identifiable on the fit rows (geometric
        #: groups; None: not decided yet, :meth:`fit` decides)
        self.hold = None if hold is None else np.asarray(hold, bool)
        #: identifiable parameters of a geometric group held at zero because the fit rows do not need
        #: them (:meth:`identify`'s forward selection by BIC); reported as 0 with no uncertainty
        self.drop = None if drop is None else np.asarray(drop, bool)
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ErrplanError(f"effect combination {names}: an effect appears twice")
        self.fd_step = fd_step
        self.max_nfev = max_nfev

    # ------------------------------------------------------------------ structure
    @property
    def names(self) -> list[str]:
        return [e.name for e in self.effects]

    @property
    def label(self) -> str:
        return "+".join(self.names) if self.effects else "none"

    @property
    def n_params(self) -> int:
        return sum(e.n_params for e in self.effects)

    @property
    def scales(self) -> np.ndarray:
        return np.array([s for e in self.effects for s in e.scales], float)

    @property
    def param_labels(self) -> list[str]:
        return [f"{e.name}.{p}" for e in self.effects for p in e.params]

    @property
    def free(self) -> np.ndarray:
        """Mask (n_params,) of the parameters that are fitted (not fixed at 0 for the robot)."""
        free = self.identifiable_mask
        if self.drop is not None:
            free &= ~self.drop
        return free

    @property
    def identifiable_mask(self) -> np.ndarray:
        """Mask (n_params,) of the parameters neither fixed for the robot nor held by QR."""
        free = np.array([not f for e in self.effects for f in e.fixed], bool)
        if self.hold is not None:
            free &= ~self.hold
        return free

    @property
    def dropped_labels(self) -> list[str]:
        """Identifiable parameters of a geometric group the fit rows do not need (held at zero)."""
        if self.drop is None:
            return []
        return [lab for lab, h in zip(self.param_labels, self.drop) if h]

    @property
    def qr_identify(self) -> bool:
        """Whether the identifiable parameters are chosen by QR (a geometric group in the combination)."""
        return any(getattr(e, "qr_identify", False) for e in self.effects)

    @property
    def held_labels(self) -> list[str]:
        """Parameters QR found not identifiable on the fit rows (held at zero)."""
        if self.hold is None:
            return []
        return [lab for lab, h in zip(self.param_labels, self.hold) if h]

    def identify(self, q, u, tracked, base, step: float = 1e-4, run=None, sparse: bool = False,
                 time=None) -> np.ndarray:
        """QR with column pivoting on the regressor of the tracked tip over the free parameters at zero
        (scaled columns: metres by 1e-3, radians by 1e-3 / GEOMETRY_LEVER, the others by their scales;
        central differences of ``step`` scaled units). Sets and returns :attr:`hold`: the columns
        with |R_ii| < QR_RTOL |R_11|. Also sets ``qr_diag_`` (|R_ii| in pivot order) and ``qr_order_``.

        ``sparse``: then, among the identifiable parameters of the groups with many parameters
        (:attr:`_Geometric.sparse`: ``joint_geometry``), keep only those the rows need
        (:meth:`_forward_select`); the others are set in :attr:`drop`. The small groups keep every
        identifiable parameter: with fewer they would be a catalogue effect under another name (a
        tracker registration without its rotation is ``tracker_offset``)."""
        from scipy.linalg import qr

        self.hold = np.zeros(self.n_params, bool)
        self.drop = None
        free = self.free
        f = self._residual_fn(q, u, tracked, base, run, time)
        z0 = np.zeros(int(free.sum()))
        r0 = f(z0) if sparse else None  # the residual at zero, before the held columns leave ``free``
        cols = []
        for j in range(len(z0)):
            dz = np.zeros_like(z0)
            dz[j] = step
            cols.append((f(z0 - dz) - f(z0 + dz)) / (2 * step))  # d model / d z
        A = np.stack(cols, axis=-1) if cols else np.zeros((0, 0))
        if A.size == 0:
            return self.hold
        _, R, piv = qr(A, mode="economic", pivoting=True)
        diag = np.abs(np.diag(R))
        keep = np.zeros(len(z0), bool)
        ref = diag[0] if len(diag) else 0.0
        keep[piv[:len(diag)][diag >= QR_RTOL * ref]] = ref > 0
        idx = np.flatnonzero(free)
        self.hold[idx[~keep]] = True
        self.qr_diag_ = diag
        self.qr_order_ = [self.param_labels[idx[k]] for k in piv]
        if sparse and any(getattr(e, "sparse", False) for e in self.effects):
            geo = np.array([getattr(e, "sparse", False) for e in self.effects for _ in e.params], bool)[idx]
            chosen = self._forward_select(A, r0, keep & ~geo, keep & geo)
            self.drop = np.zeros(self.n_params, bool)
            self.drop[idx[keep & geo & ~chosen]] = True
        return self.hold

    @staticmethod
    def _forward_select(A: np.ndarray, r0: np.ndarray, forced: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """Forward selection by BIC on the linearised fit ``r0 ~ A z``: start from the ``forced``
        columns, add the candidate column that lowers the residual most while the BIC
        (n log(RSS / n) + k log n) falls. A geometric group has many parameters (six per joint) and a
        real error is usually a few of them; fitting them all spreads the noise over every prediction
        (held-out rows far from the fit rows most). The first candidate column is always taken (the
        group is in the candidate). Returns the mask of the chosen columns."""
        n = len(r0)
        chosen = forced.copy()

        def rss(mask):
            if not mask.any():
                return float(r0 @ r0)
            z = np.linalg.lstsq(A[:, mask], r0, rcond=None)[0]
            e = r0 - A[:, mask] @ z
            return float(e @ e)

        def bic(mask, value):
            return n * np.log(max(value, 1e-300) / n) + int(mask.sum()) * np.log(n)

        best = bic(chosen, rss(chosen))
        first = True
        while True:
            trials = []
            for j in np.flatnonzero(candidates & ~chosen):
                m = chosen.copy()
                m[j] = True
                trials.append((rss(m), j, m))
            if not trials:
                return chosen
            value, j, m = min(trials, key=lambda t: t[0])
            b = bic(m, value)
            if b >= best and not first:
                return chosen
            # the group's best parameter always (a candidate named for a group has it: with none it
            # would be the model without the group, under another name)
            chosen, best, first = m, b, False

    @property
    def n_free(self) -> int:
        return int(self.free.sum())

    @property
    def free_labels(self) -> list[str]:
        return [lab for lab, f in zip(self.param_labels, self.free) if f]

    @property
    def fixed_labels(self) -> list[str]:
        return [lab for lab, f in zip(self.param_labels, self.free) if not f]

    def free_index(self) -> dict[str, list[int]]:
        """For each effect, the indices of its fitted parameters among the free ones."""
        out, i = {}, 0
        for e in self.effects:
            k = sum(not f for f in e.fixed)
            out[e.name] = list(range(i, i + k))
            i += k
        return out

    def _full(self, z_free: np.ndarray) -> np.ndarray:
        """Scaled values of every parameter from the free ones (fixed ones 0)."""
        z = np.zeros(self.n_params)
        z[self.free] = z_free
        return z

    def _split(self, values: np.ndarray) -> list[np.ndarray]:
        out, i = [], 0
        for e in self.effects:
            out.append(np.asarray(values[i:i + e.n_params], float))
            i += e.n_params
        return out

    def plant(self, base, values: Sequence[float] | None = None):
        """The base plant with every effect of the combination added."""
        values = self.values_ if values is None else np.asarray(values, float)
        p = base
        for e, v in zip(self.effects, self._split(np.asarray(values, float))):
            p = e.apply(p, v)
        return p

    def parameters(self, values: Sequence[float] | None = None) -> dict[str, dict[str, float]]:
        values = self.values_ if values is None else values
        return {e.name: e.as_dict(v) for e, v in zip(self.effects, self._split(np.asarray(values, float)))}

    def uncertainties(self) -> dict[str, dict[str, float]]:
        return {e.name: e.as_dict(v) for e, v in zip(self.effects, self._split(self.sigma_))}

    def predict(self, base, q: np.ndarray, u: np.ndarray | None, values: Sequence[float] | None = None,
                run: np.ndarray | None = None, time: np.ndarray | None = None) -> np.ndarray:
        return predict_tracked(self.plant(base, values), q, u, run, time)

    # ------------------------------------------------------------------ fitting
    def _residual_fn(self, q, u, tracked, base, run=None, time=None):
        """Residual (tracked rows x d,) as a function of the free parameters in scaled units. Rows
        without a tracked tip (NaN: dropouts) have no residual; they stay in the prediction, whose
        history (backlash, tracker latency) runs through them."""
        scales = self.scales
        tracked = np.asarray(tracked, float)
        rows = np.all(np.isfinite(tracked), axis=1)
        rows = None if rows.all() else rows
        if rows is not None:
            tracked = tracked[rows]
        base = with_gravity_cache(base)

        def f(z: np.ndarray) -> np.ndarray:
            with np.errstate(invalid="ignore", divide="ignore"):
                pred = predict_tracked(self.plant(base, self._full(z) * scales), q, u, run, time)
                r = (tracked - (pred if rows is None else pred[rows])).ravel()
            # a parameter value that breaks the geometry (shaft out of the port) is a huge misfit,
            # never a NaN inside the optimiser
            return np.where(np.isfinite(r), r, 1.0)

        return f

    def _jac(self, f, z: np.ndarray) -> np.ndarray:
        h = self.fd_step
        cols = []
        for j in range(len(z)):
            dz = np.zeros_like(z)
            dz[j] = h
            cols.append((f(z + dz) - f(z - dz)) / (2 * h))
        return np.stack(cols, axis=-1)

    def fit(self, q: np.ndarray, u: np.ndarray | None, tracked: np.ndarray, base,
            x0: Sequence[float] | None = None, run: np.ndarray | None = None,
            time: np.ndarray | None = None) -> "EffectModel":
        """Fit the combination to measured rows: encoder angles ``q`` (n, N) rad, friction's
        directions ``u`` (n, d) (the motion each row's command produced under the declared model,
        :meth:`errplan.experiment.MeasuredData.commanded_directions`), tracked tips ``tracked``
        (n, d) m (NaN rows: dropouts, no residual); ``base`` the declared :class:`Plant`. ``x0`` a
        start (physics.md units, default zero); ``run``, ``time`` the rows' runs and times (history
        effects). Returns self."""
        from scipy.optimize import least_squares

        q = np.asarray(q, float)
        n = int(np.sum(np.all(np.isfinite(np.asarray(tracked, float)), axis=1)))  # rows with a residual
        d = np.shape(tracked)[-1]
        P = self.n_params
        if self.qr_identify and self.hold is None:
            self.identify(q, u, tracked, base, run=run, sparse=True, time=time)
        free = self.free
        p = int(free.sum())
        self.n_obs_ = d * n
        f = self._residual_fn(q, u, tracked, base, run, time)
        all_scales = self.scales
        scales = all_scales[free]
        if p == 0:
            r = f(np.zeros(0))
            self.values_ = np.zeros(P)
            self.cov_ = np.full((P, P), np.nan)
            self.sigma_ = np.full(P, np.nan)
            self.rss_ = float(r @ r)
            self.condition_ = 1.0
            self.correlation_ = np.zeros((0, 0))
            self.max_correlation_ = 0.0
            self.identifiable_ = P == 0
            self.why_ = "" if P == 0 else "no parameter of it can be identified on this robot"
            self.success_ = True
            self.nfev_ = 1
            return self
        if d * n <= p:
            raise ErrplanError(f"{self.label}: {n} rows cannot fit {p} parameters")
        z0 = np.zeros(p) if x0 is None else np.asarray(x0, float)[free] / scales
        hist = np.array([getattr(e, "history", False) for e in self.effects for _ in e.params], bool)[free]
        if x0 is None and hist.any():
            # a play is not smooth at zero (the clip): start from the best of a few sizes, 0.5-8 scales
            starts = [np.where(hist, c, 0.0) for c in (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)]
            z0 = min(starts, key=lambda z: float(np.sum(f(z) ** 2)))
        # parameters with a range (tracker_latency: 0 .. 5 steps) and their own starting sizes
        per = [e for e, f_ in zip([e for e in self.effects for _ in e.params], free) if f_]  # effect of each free param
        lo = np.array([(getattr(e, "bounds", None) or (-np.inf, np.inf))[0] for e in per], float)
        hi = np.array([(getattr(e, "bounds", None) or (-np.inf, np.inf))[1] for e in per], float)
        bounded = bool(np.any(np.isfinite(lo) | np.isfinite(hi)))
        if bounded:
            z0 = np.clip(z0, lo, hi)
            own = [(j, e.starts) for j, e in enumerate(per) if getattr(e, "bounds", None) and getattr(e, "starts", None)]
            if x0 is None and own:
                trials = [z0]
                for j, cs in own:
                    for c in cs:
                        z = z0.copy()
                        z[j] = c
                        trials.append(z)
                z0 = min(trials, key=lambda z: float(np.sum(f(z) ** 2)))
            sol = least_squares(f, z0, jac=lambda z: self._jac(f, z), method="trf", bounds=(lo, hi),
                                max_nfev=self.max_nfev, xtol=1e-10, ftol=1e-12, gtol=1e-12)
        else:
            sol = least_squares(f, z0, jac=lambda z: self._jac(f, z), method="lm", max_nfev=self.max_nfev,
                                xtol=1e-10, ftol=1e-12, gtol=1e-12)
        z = sol.x
        r = f(z)
        J = self._jac(f, z)
        self.values_ = self._full(z) * all_scales
        hist_all = np.array([getattr(e, "history", False) for e in self.effects for _ in e.params], bool)
        self.values_ = np.where(hist_all, np.abs(self.values_), self.values_)  # a play's half-width is >= 0
        self.rss_ = float(r @ r)
        self.nfev_ = int(sol.nfev)
        self.success_ = bool(sol.success) and bool(np.all(np.isfinite(z)))
        # identifiability on the column-normalised Jacobian
        norms = np.linalg.norm(J, axis=0)
        why = []
        dead = norms <= 1e-12 * max(1.0, float(np.max(norms)) if len(norms) else 1.0)
        if np.any(dead):
            why.append("no data depend on " + ", ".join(np.array(self.free_labels)[dead]))
        Jn = J / np.where(dead, 1.0, norms)
        _, sv, Vt = np.linalg.svd(Jn, full_matrices=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 1e-14 * sv[0] else float("inf")
        s2 = self.rss_ / max(d * n - p, 1)
        if np.isfinite(cond) and not np.any(dead):
            A = (Vt.T / sv ** 2) @ Vt          # (Jn^T Jn)^-1, positive definite
            d = np.sqrt(np.diag(A))
            corr = A / np.outer(d, d)
            cov_z = s2 * (A / np.outer(norms, norms))
        else:
            corr = np.full((p, p), np.nan)
            np.fill_diagonal(corr, 1.0)
            cov_z = np.full((p, p), np.inf)
        off = np.abs(corr - np.eye(p))
        if not np.all(np.isfinite(corr)):
            self.max_correlation_ = 1.0
        else:
            self.max_correlation_ = float(np.max(off)) if p > 1 else 0.0
        self.condition_ = cond
        self.correlation_ = corr
        cov = np.full((P, P), np.nan)
        cov[np.ix_(free, free)] = cov_z * np.outer(scales, scales)
        self.cov_ = cov
        self.sigma_ = np.sqrt(np.diag(cov))
        if cond > MAX_CONDITION:  # one threshold for every candidate, geometric groups included (QR keeps
            # the parameters the rows see at all; how well they see them is this number)
            why.append(f"condition number {cond:.3g} > {MAX_CONDITION:g}")
        if self.max_correlation_ > MAX_CORRELATION and not self.qr_identify:
            i, j = np.unravel_index(int(np.nanargmax(np.where(np.isfinite(off), off, 2.0))), off.shape)
            labels = self.free_labels
            why.append(f"{labels[i]} and {labels[j]} correlate {corr[i, j]:+.4f}")
        if not self.success_:
            why.append(f"the fit did not converge ({sol.message})")
        self.identifiable_ = not why
        self.why_ = "; ".join(why)
        return self
