"""Scenario files: TOML -> validated, immutable :class:`Scenario`.

Every table of ``docs/interfaces.md`` has a frozen dataclass here. :func:`read_scenario`
reads a file once and validates every key; a malformed file raises one
:class:`ScenarioError` that names the key, the value and what was expected.
Nothing else lives in this module: it builds no robot. The checks that need the robot (a URDF that
loads, a port the shaft can reach) are :func:`errplan.kinematics.check_scenario`; :func:`errplan.load_scenario`
does both.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore

from . import packages
from .errors import ScenarioError

METRICS = ("phi_hat_max", "G_norm", "phi_max", "rho_star")
JACOBIANS = ("rigid", "flexion")
TOLERANCE_KINDS = ("port", "insertion_band", "tip_load", "tracker_noise", "port_placement")
#: kinds of a several-arm scenario (``[[arm]]``): answered for the whole setup, not per arm
SETUP_TOLERANCE_KINDS = ("triad_placement", "setup_placement")
EFFECT_PARAMS: dict[str, tuple[str, ...]] = {
    "port_offset": ("dy", "dz"),
    "joint_offset": ("dq1", "dq2"),
    "tracker_offset": ("by", "bz"),
    "gravity_sag": ("c1", "c2", "c3"),
    "shaft_flexion": ("fy", "fz"),
    "port_friction": ("fa", "fn"),
    # geometry and backlash (physics.md "Closing the loop when the catalogue lacks the effect")
    "link_length": ("dl1", "dl2"),
    "instrument_length": ("dL",),
    "tracker_registration": ("rx", "by", "bz"),
    "backlash": ("b1", "b2"),
    "joint_geometry": (),
    # a bench as it records (physics.md "Measured data as a bench records it"): tau in s with
    # [sensors] step_time, else in steps
    "tracker_latency": ("tau",),
}
#: effects of one dimension only: the planar arm has link lengths, a URDF arm joint origins
EFFECT_DIMS = {"link_length": 2, "joint_geometry": 3}


def joint_geometry_keys(n: int) -> tuple[str, ...]:
    """The ``joint_geometry`` keys of an arm with ``n`` actuated joints: each joint's origin ``dx_i``,
    ``dy_i``, ``dz_i``, ``rx_i``, ``ry_i``, ``rz_i`` (i = 1 .. n), then the wrist link's origin
    ``dx_<n+1>``, ``dy_<n+1>``, ``dz_<n+1>``."""
    return (tuple(f"{k}_{i + 1}" for i in range(n) for k in ("dx", "dy", "dz", "rx", "ry", "rz"))
            + tuple(f"{k}_{n + 1}" for k in ("dx", "dy", "dz")))


def effect_params(name: str, dim: int = 2, n_joints: int = 2) -> tuple[str, ...]:
    """Parameter names of effect ``name`` (docs/physics.md): the planar table, or its 3-D version."""
    if EFFECT_DIMS.get(name, dim) != dim:
        raise KeyError(name)
    if dim == 2:
        return EFFECT_PARAMS[name]
    return {
        "link_length": (),
        "instrument_length": ("dL",),
        "tracker_registration": ("rx", "ry", "rz", "bx", "by", "bz"),
        "backlash": tuple(f"b{i + 1}" for i in range(n_joints)),
        "joint_geometry": joint_geometry_keys(n_joints),
        "port_offset": ("dx", "dy", "dz"),
        "joint_offset": tuple(f"dq{i + 1}" for i in range(n_joints)),
        "tracker_offset": ("bx", "by", "bz"),
        "gravity_sag": tuple(f"c{i + 1}" for i in range(n_joints)),
        "shaft_flexion": ("fx", "fy", "fz"),
        "port_friction": ("fa", "fn"),
        "tracker_latency": ("tau",),
    }[name]


AXES = {2: ("y", "z"), 3: ("x", "y", "z")}


# ----------------------------------------------------------------------------- tables
@dataclass(frozen=True)
class Robot:
    base: tuple[float, float] = (0.210, -0.210)
    link_lengths: tuple[float, float] = (0.210, 0.210)
    home_angles: tuple[float, float] = (0.0, -math.pi / 2)
    joint_limits: tuple[tuple[float, float], tuple[float, float]] = ((-1.9, 1.2), (-0.7, 1.0))
    joint_sum_limits: tuple[float, float] = (-0.3, 2.8)


@dataclass(frozen=True)
class CoupledLimit:
    """``lo <= sum(coeffs[i] * q[joints[i]]) <= hi``: a linear joint limit (P1's limit on q1 + q2)."""

    joints: tuple[str, ...]
    coeffs: tuple[float, ...]
    lo: float
    hi: float


@dataclass(frozen=True)
class UrdfRobot:
    """A spatial arm from a URDF (docs/physics.md "Spatial robots"): the actuated ``joints`` place the
    origin of link ``wrist``; other joints on the chain are held at ``fixed_joints`` (default 0).
    Paths are absolute (resolved against the scenario file)."""

    urdf: str
    joints: tuple[str, ...]
    wrist: str
    base_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    joint_limits: tuple[tuple[float, float], ...] | None = None
    fixed_joints: tuple[tuple[str, float], ...] = ()
    coupled_limits: tuple[CoupledLimit, ...] = ()
    package_path: tuple[str, ...] = ()


@dataclass(frozen=True)
class Instrument:
    length: float = 0.320
    flexural_rigidity: float | None = None


@dataclass(frozen=True)
class Port:
    position: tuple[float, ...]  # [y, z] or [x, y, z], m
    estimate: tuple[float, ...]


@dataclass(frozen=True)
class Controller:
    gain: float = 1.0
    jacobian: str = "rigid"


@dataclass(frozen=True)
class SensorNoise:
    position: float = 0.0
    angle: float = 0.0


@dataclass(frozen=True)
class Uncertainty:
    """Bounded error set. Ports are ``estimate + offset``; ``None`` means "not uncertain"."""

    port_y: tuple[float, float] | None = None
    port_z: tuple[float, float] | None = None
    tip_force_over_ei: tuple[float, float] | None = None
    sensor_noise: SensorNoise | None = None
    samples: int = 5  # samples per uncertain axis before local refinement
    port_x: tuple[float, float] | None = None  # spatial scenarios only

    @property
    def declared(self) -> bool:
        return any(v is not None for v in (self.port_x, self.port_y, self.port_z, self.tip_force_over_ei,
                                           self.sensor_noise))


@dataclass(frozen=True)
class Sensors:
    """``[sensors]``: the sensor noise of simulated data, and how ``errplan experiment`` records a bench
    (docs/physics.md "Measured data as a bench records it"; every one of these off by default):
    ``step_time`` (s: a ``time`` column, steps this long on average; None: no time column),
    ``step_jitter`` (relative, each step's duration uniform within ±), ``dropout_rate`` (share of rows
    without a tracked tip) in bursts of 1..``dropout_burst`` rows, ``outlier_rate`` (share of rows
    whose tracked tip is far off) at a distance uniform in ``outlier_size`` (m), random direction."""

    tracker_sigma: float = 0.0002
    encoder_sigma: float = 0.0
    step_time: float | None = None
    step_jitter: float = 0.0
    dropout_rate: float = 0.0
    dropout_burst: int = 1
    outlier_rate: float = 0.0
    outlier_size: tuple[float, float] = (0.003, 0.010)

    @property
    def records(self) -> bool:
        """Whether the bench records anything beyond the clean table (time, dropouts, outliers)."""
        return self.step_time is not None or self.dropout_rate > 0 or self.outlier_rate > 0


@dataclass(frozen=True)
class Fields:
    resolution: float = 0.002
    region: Mapping[str, tuple[float, float]] | None = None  # {axis: (lo, hi)}: the task region


@dataclass(frozen=True)
class Planner:
    metric: str = "phi_hat_max"
    weight: float = 1.0
    planner: str = "BITstar"
    time: float | None = None  # s per query: a safety cap only (a plan it cuts depends on the machine)
    seed: int = 1
    certifiable: bool = True
    certify_margin: float = 0.02
    iterations: int | None = None  # the search's budget per query (None: the planner's default)


#: the largest ``[planner] iterations`` (a search budget beyond any planning run)
MAX_ITERATIONS = 10**9


@dataclass(frozen=True)
class Query:
    name: str
    start: tuple[float, ...]
    goal: tuple[float, ...]


@dataclass(frozen=True)
class Tolerance:
    name: str
    kind: str
    options: Mapping[str, Any] = field(default_factory=dict)

    def get(self, key: str, default: Any = None) -> Any:
        return self.options.get(key, default)


# ----------------------------------------------------------------------------- anatomy
OBSTACLE_SHAPES = ("sphere", "capsule", "box", "mesh")
WALL_SHAPES = ("ellipsoid", "mesh")
MESH_SUFFIXES = (".stl", ".obj", ".ply")


@dataclass(frozen=True)
class Obstacle:
    """One obstacle of ``[anatomy]`` (docs/interfaces.md "Anatomy"), plain data: ``shape`` is
    ``"sphere"`` (``center``, ``radius``), ``"capsule"`` (``a``, ``b``, ``radius``), ``"box"``
    (``center``, ``half_extents``, ``rpy``) or ``"mesh"`` (``file``, absolute; ``scale``,
    ``position``, ``rpy``). Unused fields keep their defaults. m, rad."""

    name: str
    shape: str
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.0
    a: tuple[float, float, float] = (0.0, 0.0, 0.0)
    b: tuple[float, float, float] = (0.0, 0.0, 0.0)
    half_extents: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    file: str = ""
    scale: float = 1.0
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class BodyWall:
    """The inner surface of the insufflated abdomen: ``"ellipsoid"`` (``center``, ``radii``) or
    ``"mesh"`` (``file``, ``scale``, ``position``, ``rpy`` as an obstacle mesh)."""

    shape: str
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radii: tuple[float, float, float] = (0.0, 0.0, 0.0)
    file: str = ""
    scale: float = 1.0
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Anatomy:
    """``[anatomy]``: the clearance (m) kept from every obstacle, the obstacles, the body wall."""

    clearance: float = 0.0
    obstacles: tuple[Obstacle, ...] = ()
    body_wall: BodyWall | None = None


@dataclass(frozen=True)
class Scenario:
    """A validated scenario: one frozen dataclass per TOML table (the scenario reference lists every key).

    Made by :func:`errplan.load_scenario` (a file) or :func:`errplan.parse_scenario` (a parsed document);
    plain data that builds nothing. ``with_`` returns a copy with some tables replaced.

    Attributes
    ----------
    name : str
        The scenario's name.
    robot : Robot or UrdfRobot
        ``[robot]``: P1's planar arm, or a URDF arm (then the scenario is spatial).
    instrument, port, controller, uncertainty, sensors, fields, planner
        The tables of the same names.
    queries : tuple of Query
        ``[[query]]``, in file order.
    tolerances : tuple of Tolerance
        ``[[tolerance]]``, in file order.
    effects : Mapping
        ``[effects.NAME]``: ``{effect: {parameter: value}}`` present in the truth.
    anatomy : Anatomy or None
        ``[anatomy]`` (spatial scenarios only).

    Examples
    --------
    >>> import errplan
    >>> sc = errplan.load_scenario("scenarios/beasley2004_port.toml")
    >>> sc.dim, sc.axes, sc.instrument.length
    (2, ('y', 'z'), 0.32)
    >>> sc.with_(effects={"port_offset": {"dy": 0.002}}).effects["port_offset"]["dy"]
    0.002
    """

    name: str
    robot: Robot | UrdfRobot
    instrument: Instrument
    port: Port
    controller: Controller
    uncertainty: Uncertainty
    sensors: Sensors
    fields: Fields
    planner: Planner
    queries: tuple[Query, ...] = ()
    tolerances: tuple[Tolerance, ...] = ()
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    description: str = ""
    source: str = "<memory>"
    anatomy: Anatomy | None = None  # [anatomy] (spatial scenarios only)
    view: Any = None  # an Endoscope whose view every planned tip keeps ([endoscope] keep_visible; Setup.moving)
    held_arms: Any = None  # HeldArms: the other arms, held at rest, the moving arm's links keep clear of (Setup.moving)

    @property
    def dim(self) -> int:
        """2 for P1's planar arm ([y, z]), 3 for a URDF arm ([x, y, z])."""
        return 3 if isinstance(self.robot, UrdfRobot) else 2

    @property
    def axes(self) -> tuple[str, ...]:
        return AXES[self.dim]

    def with_(self, **changes: Any) -> "Scenario":
        """A copy with some top-level tables replaced (dataclasses.replace)."""
        return replace(self, **changes)


# ----------------------------------------------------------------------------- helpers
class _Ctx:
    def __init__(self, source: str):
        self.source = source

    def fail(self, key: str, value: Any, expected: str) -> ScenarioError:
        return ScenarioError(f"{self.source}: {key} = {value!r}: expected {expected}")


def _unique_name(ctx, t: dict, where: str, default: str, names: set, what: str) -> str:
    """The ``name`` of one entry of an array of tables (``default`` when absent): a non-empty string no
    other entry has; added to ``names``."""
    name = t.get("name", default)
    if not isinstance(name, str) or not name:
        raise ctx.fail(where + "name", name, "a non-empty string")
    if name in names:
        raise ctx.fail(where + "name", name, f"a name used by no other {what}")
    names.add(name)
    return name


def _short(v: Any) -> str:
    """A value for an error message: short values as written, tables and long lists abbreviated (an
    unknown ``[[arm]]`` key must not print every arm)."""
    if isinstance(v, dict):
        return "a table {" + ", ".join(list(map(str, v))[:6]) + (", ..." if len(v) > 6 else "") + "}"
    if isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
        return f"an array of {len(v)} table{'s' if len(v) != 1 else ''}"
    r = repr(v)
    return r if len(r) <= 80 else r[:77] + "..."


class _Short(str):
    """A value already abbreviated by :func:`_short` (printed without quotes)."""

    def __repr__(self) -> str:
        return str(self)


def _check_keys(ctx: _Ctx, table: Mapping[str, Any], allowed: tuple[str, ...], where: str) -> None:
    for k in table:
        if k not in allowed:
            raise ctx.fail(f"{where}{k}", _Short(_short(table[k])), f"one of the keys {', '.join(allowed)} "
                           "(unknown key)")


def _table(ctx: _Ctx, doc: Mapping[str, Any], key: str, required: bool) -> Mapping[str, Any]:
    if key not in doc:
        if required:
            raise ctx.fail(f"[{key}]", None, "a table (missing)")
        return {}
    v = doc[key]
    if not isinstance(v, dict):
        raise ctx.fail(f"[{key}]", v, "a table")
    return v


def _num(ctx: _Ctx, v: Any, key: str, *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ctx.fail(key, v, "a number")
    x = float(v)
    if not math.isfinite(x):
        raise ctx.fail(key, v, "a finite number")
    if positive and x <= 0:
        raise ctx.fail(key, v, "a number > 0")
    if nonneg and x < 0:
        raise ctx.fail(key, v, "a number >= 0")
    return x


#: Lengths and coordinates (m) beyond this are implausible for a surgical robot: a value in millimetres.
MAX_METRES = 5.0
#: Angles (rad) beyond this (2 pi and a rounding's margin) are a turn and more: a value in degrees.
MAX_RADIANS = 2.0 * math.pi + 1e-3


def _metres(ctx: _Ctx, values: Sequence[float], key: str, given: Any, bound: float = MAX_METRES) -> None:
    """Lengths or coordinates of ``key`` (m): one too large for metres (beyond ``bound``) that millimetres
    would explain is an error that names the key and the likely slip, with the value it meant. (A value
    that is absurd in millimetres too is left to the checks of what it would cost: the memory check.)"""
    for x in values:
        if bound < abs(x) <= 1000.0 * bound:
            raise ScenarioError(f"{ctx.source}: {key} = {_short(given)}: {x:g} m is implausibly large for a "
                                f"surgical robot (more than {bound:g} m); errplan takes metres: if {x:g} is in "
                                f"millimetres, write {x / 1000:g}")


def _radians(ctx: _Ctx, values: Sequence[float], key: str, given: Any, metres_too: bool = False) -> None:
    """Angles of ``key`` (rad): one beyond +-2 pi is an error that names the key and the likely slip
    (degrees), with the value it meant. ``metres_too``: a prismatic joint's value (m) is also possible."""
    for x in values:
        if abs(x) > MAX_RADIANS:
            alt = " (or, for a prismatic joint, metres)" if metres_too else ""
            hint = f": if {x:g} is in degrees, write {math.radians(x):.6g}" if abs(x) <= 720.0 else ""
            raise ScenarioError(f"{ctx.source}: {key} = {_short(given)}: {x:g} is beyond +-2 pi, more than a "
                                f"full turn; errplan takes radians{alt}{hint}")


def _pair(ctx: _Ctx, v: Any, key: str, *, ordered: bool = False) -> tuple[float, float]:
    if not isinstance(v, list) or len(v) != 2:
        raise ctx.fail(key, v, "a list of two numbers")
    a, b = (_num(ctx, x, key) for x in v)
    if ordered and a > b:
        raise ctx.fail(key, v, "[low, high] with low <= high (limits reversed)")
    return (a, b)


def _vec(ctx: _Ctx, v: Any, key: str, d: int) -> tuple[float, ...]:
    """A point of the scenario's dimension: ``[y, z]`` (d = 2) or ``[x, y, z]`` (d = 3)."""
    if not isinstance(v, list) or len(v) != d:
        raise ctx.fail(key, v, f"a list of {d} numbers [{', '.join(AXES[d])}] (m)")
    return tuple(_num(ctx, x, key) for x in v)


def _region(ctx: _Ctx, r: Any, key: str, d: int) -> dict[str, tuple[float, float]]:
    """``{ x = [lo, hi], y = [lo, hi], z = [lo, hi] }`` (x only in 3-D); ``lo == hi`` is a slice."""
    axes = AXES[d]
    form = "{ " + ", ".join(f"{a} = [lo, hi]" for a in axes) + " }"
    if not isinstance(r, dict) or set(r) != set(axes):
        raise ctx.fail(key, r, form)
    return {a: _pair(ctx, r[a], f"{key}.{a}", ordered=True) for a in axes}


def _get(ctx: _Ctx, t: Mapping[str, Any], key: str, where: str, default: Any = ..., ) -> Any:
    if key in t:
        return t[key]
    if default is ...:
        raise ctx.fail(f"{where}{key}", None, "a value (missing key)")
    return default


# ----------------------------------------------------------------------------- the keys of every table
#: Every key each scenario table accepts, as data: the parser checks tables against these
#: (:func:`_check_keys`), and the scenario reference of the documentation is generated from them.
#: ``"[robot]"`` is a planar arm, ``"[robot] urdf"`` a spatial one; ``"[uncertainty] 3-D"`` holds the keys
#: a spatial scenario adds. ``[[tolerance]]`` keys per kind: :data:`TOLERANCE_KEYS`; ``[effects.NAME]``:
#: :data:`EFFECT_PARAMS`.
TABLE_KEYS: dict[str, tuple[str, ...]] = {
    "": ("name", "description", "robot", "instrument", "port", "controller", "uncertainty",
         "sensors", "fields", "planner", "query", "tolerance", "effects", "anatomy"),
    "[robot]": ("base", "link_lengths", "home_angles", "joint_limits", "joint_sum_limits"),
    "[robot] urdf": ("urdf", "package_path", "joints", "wrist", "base_position", "base_rpy", "joint_limits",
                     "fixed_joints", "coupled_limits"),
    "[robot] coupled_limits": ("joints", "coeffs", "range"),
    "[instrument]": ("length", "flexural_rigidity"),
    "[port]": ("position", "estimate"),
    "[controller]": ("gain", "jacobian"),
    "[uncertainty]": ("port_y", "port_z", "tip_force_over_ei", "sensor_noise", "samples"),
    "[uncertainty] 3-D": ("port_x",),
    "sensor_noise": ("position", "angle"),
    "[sensors]": ("tracker_sigma", "encoder_sigma", "step_time", "step_jitter", "dropout_rate", "dropout_burst",
                  "outlier_rate", "outlier_size"),
    "[fields]": ("resolution", "region"),
    "[planner]": ("metric", "weight", "planner", "iterations", "time", "seed", "certifiable", "certify_margin"),
    "[[query]]": ("name", "start", "goal"),
    "[[tolerance]]": ("name", "kind"),
    "[anatomy]": ("clearance", "obstacle", "body_wall"),
    "[[anatomy.obstacle]]": ("name", "shape"),
    "[anatomy.body_wall] ellipsoid": ("shape", "center", "radii"),
    "[anatomy.body_wall] mesh": ("shape", "file", "scale", "position", "rpy"),
    # several instruments (:func:`setup_from_dict`): the top level adds these, the instrument tables
    # move into each ``[[arm]]`` (``[arm.robot]`` ... take the keys of ``[robot]`` ...)
    "several instruments": ("arm", "endoscope", "setup"),
    "[[arm]]": ("name", "rest", "robot", "instrument", "port", "controller", "uncertainty"),
    "[endoscope]": ("port", "look_at", "insertion", "fov", "depth", "uncertainty", "keep_visible"),
    "[endoscope] port": ("estimate", "position"),
    "[endoscope] uncertainty": ("port_x", "port_y", "port_z"),
    "[setup]": ("shaft_clearance", "arm_clearance", "patient_clearance"),
    "[[query]] several instruments": ("arm",),
}
#: ``[[anatomy.obstacle]]`` keys per ``shape`` (besides ``name`` and ``shape``).
OBSTACLE_KEYS: dict[str, tuple[str, ...]] = {
    "sphere": ("center", "radius"), "capsule": ("a", "b", "radius"),
    "box": ("center", "half_extents", "rpy"), "mesh": ("file", "scale", "position", "rpy"),
}


# ----------------------------------------------------------------------------- parsing
def _robot(ctx: _Ctx, t: Mapping[str, Any]) -> Robot:
    w = "[robot] "
    _check_keys(ctx, t, TABLE_KEYS["[robot]"], w)
    d = Robot()
    base = _pair(ctx, _get(ctx, t, "base", w, list(d.base)), w + "base")
    _metres(ctx, base, w + "base", list(base))
    ll = _pair(ctx, _get(ctx, t, "link_lengths", w, list(d.link_lengths)), w + "link_lengths")
    if min(ll) <= 0:
        raise ctx.fail(w + "link_lengths", list(ll), "two lengths > 0")
    _metres(ctx, ll, w + "link_lengths", list(ll))
    home = _pair(ctx, _get(ctx, t, "home_angles", w, list(d.home_angles)), w + "home_angles")
    _radians(ctx, home, w + "home_angles", list(home))
    jl = _get(ctx, t, "joint_limits", w, [list(x) for x in d.joint_limits])
    if not isinstance(jl, list) or len(jl) != 2:
        raise ctx.fail(w + "joint_limits", jl, "[[q1_lo, q1_hi], [q2_lo, q2_hi]]")
    jl2 = tuple(_pair(ctx, x, w + f"joint_limits[{i}]", ordered=True) for i, x in enumerate(jl))
    for i, x in enumerate(jl2):
        _radians(ctx, x, w + f"joint_limits[{i}]", list(x))
    js = _pair(ctx, _get(ctx, t, "joint_sum_limits", w, list(d.joint_sum_limits)), w + "joint_sum_limits", ordered=True)
    return Robot(base, ll, home, jl2, js)  # type: ignore[arg-type]


def _instrument(ctx: _Ctx, t: Mapping[str, Any]) -> Instrument:
    w = "[instrument] "
    _check_keys(ctx, t, TABLE_KEYS["[instrument]"], w)
    length = _num(ctx, _get(ctx, t, "length", w), w + "length", positive=True)
    _metres(ctx, [length], w + "length", t["length"])
    ei = t.get("flexural_rigidity")
    return Instrument(length, None if ei is None else _num(ctx, ei, w + "flexural_rigidity", positive=True))


def _port(ctx: _Ctx, t: Mapping[str, Any], d: int = 2) -> Port:
    w = "[port] "
    _check_keys(ctx, t, TABLE_KEYS["[port]"], w)
    pos = _vec(ctx, _get(ctx, t, "position", w), w + "position", d)
    est = _vec(ctx, _get(ctx, t, "estimate", w, list(pos)), w + "estimate", d)
    _metres(ctx, pos, w + "position", list(pos))
    _metres(ctx, est, w + "estimate", list(est))
    return Port(pos, est)


def _urdf_robot(ctx: _Ctx, t: Mapping[str, Any], base_dir: Path) -> UrdfRobot:
    """``[robot]`` of a spatial scenario (interfaces.md "Spatial scenarios")."""
    w = "[robot] "
    _check_keys(ctx, t, TABLE_KEYS["[robot] urdf"], w)
    urdf = _get(ctx, t, "urdf", w)
    if not isinstance(urdf, str) or not urdf:
        raise ctx.fail(w + "urdf", urdf, "the path of a URDF file (relative to the scenario file) or a "
                                         "package://NAME/PATH URI")
    pkg = t.get("package_path", [])
    if isinstance(pkg, str):
        pkg = [pkg]
    if not isinstance(pkg, list) or not all(isinstance(x, str) and x for x in pkg):
        raise ctx.fail(w + "package_path", pkg, "a list of directories (relative to the scenario file)")
    if urdf.startswith(packages.SCHEME):
        if packages.split_uri(urdf) is None:
            raise ctx.fail(w + "urdf", urdf, "package://NAME/PATH (a package name, then the file's path in it)")
        dirs = packages.search_dirs(pkg, base_dir)
        found = packages.resolve(urdf, dirs)
        if found is None:
            raise ctx.fail(w + "urdf", urdf, "a file of an installed robot-description package: not found in "
                           "package_path, ROS_PACKAGE_PATH or this environment's description packages "
                           f"({', '.join(str(d) for d in dirs) or 'none'}); for example-robot-data arms: "
                           "pip install example-robot-data")
        urdf_path = found
    else:
        urdf_path = (base_dir / urdf).resolve()
    joints = _get(ctx, t, "joints", w)
    if (not isinstance(joints, list) or not joints or not all(isinstance(j, str) and j for j in joints)
            or len(set(joints)) != len(joints)):
        raise ctx.fail(w + "joints", joints, "a list of distinct joint names of the URDF (the actuated joints)")
    if len(joints) != 3:
        raise ctx.fail(w + "joints", joints, "three actuated joints that place the wrist in 3-D")
    wrist = _get(ctx, t, "wrist", w)
    if not isinstance(wrist, str) or not wrist:
        raise ctx.fail(w + "wrist", wrist, "the name of the URDF link whose origin is the instrument's pivot")
    bp = _vec(ctx, t.get("base_position", [0.0, 0.0, 0.0]), w + "base_position", 3)
    rpy = t.get("base_rpy", [0.0, 0.0, 0.0])
    if not isinstance(rpy, list) or len(rpy) != 3:
        raise ctx.fail(w + "base_rpy", rpy, "a list of 3 angles [roll, pitch, yaw] (rad)")
    rpy = tuple(_num(ctx, x, w + "base_rpy") for x in rpy)
    _metres(ctx, bp, w + "base_position", list(bp))
    _radians(ctx, rpy, w + "base_rpy", list(rpy))
    jl = None
    if "joint_limits" in t:
        v = t["joint_limits"]
        if not isinstance(v, list) or len(v) != len(joints):
            raise ctx.fail(w + "joint_limits", v, f"{len(joints)} pairs [lo, hi], one per actuated joint (rad or m)")
        jl = tuple(_pair(ctx, x, w + f"joint_limits[{i}]", ordered=True) for i, x in enumerate(v))
        for i, x in enumerate(jl):
            _radians(ctx, x, w + f"joint_limits[{i}]", list(x), metres_too=True)
    fj = t.get("fixed_joints", {})
    if not isinstance(fj, dict):
        raise ctx.fail(w + "fixed_joints", fj, "a table { joint = value }")
    fixed = tuple((str(k), _num(ctx, v, w + f"fixed_joints.{k}")) for k, v in fj.items())
    for k, v in fixed:
        _radians(ctx, [v], w + f"fixed_joints.{k}", v, metres_too=True)
    for k, _ in fixed:
        if k in joints:
            raise ctx.fail(w + f"fixed_joints.{k}", dict(fj)[k], "a joint that is not actuated (it is in joints)")
    cl = t.get("coupled_limits", [])
    if not isinstance(cl, list):
        raise ctx.fail(w + "coupled_limits", cl, "a list of { joints = [...], coeffs = [...], range = [lo, hi] }")
    coupled = []
    for i, c in enumerate(cl):
        key = w + f"coupled_limits[{i}]"
        if not isinstance(c, dict):
            raise ctx.fail(key, c, "a table { joints = [...], coeffs = [...], range = [lo, hi] }")
        _check_keys(ctx, c, TABLE_KEYS["[robot] coupled_limits"], key + ".")
        cj = _get(ctx, c, "joints", key + ".")
        if not isinstance(cj, list) or not cj or not all(j in joints for j in cj):
            raise ctx.fail(key + ".joints", cj, f"a list of actuated joints ({', '.join(joints)})")
        co = c.get("coeffs", [1.0] * len(cj))
        if not isinstance(co, list) or len(co) != len(cj):
            raise ctx.fail(key + ".coeffs", co, f"{len(cj)} numbers, one per joint")
        co = tuple(_num(ctx, x, key + ".coeffs") for x in co)
        lo, hi = _pair(ctx, _get(ctx, c, "range", key + "."), key + ".range", ordered=True)
        coupled.append(CoupledLimit(tuple(cj), co, lo, hi))
    return UrdfRobot(urdf=str(urdf_path), joints=tuple(joints), wrist=wrist, base_position=bp, base_rpy=rpy,
                     joint_limits=jl, fixed_joints=fixed, coupled_limits=tuple(coupled),
                     package_path=tuple(str((base_dir / x).resolve()) for x in pkg))


def _controller(ctx: _Ctx, t: Mapping[str, Any]) -> Controller:
    w = "[controller] "
    _check_keys(ctx, t, TABLE_KEYS["[controller]"], w)
    gain = _num(ctx, _get(ctx, t, "gain", w, 1.0), w + "gain", positive=True)
    jac = _get(ctx, t, "jacobian", w, "rigid")
    if jac not in JACOBIANS:
        raise ctx.fail(w + "jacobian", jac, " or ".join(f'"{j}"' for j in JACOBIANS))
    return Controller(gain, jac)


def _noise(ctx: _Ctx, v: Any, key: str) -> SensorNoise:
    if not isinstance(v, dict):
        raise ctx.fail(key, v, "a table {position = m, angle = rad}")
    _check_keys(ctx, v, TABLE_KEYS["sensor_noise"], key + ".")
    return SensorNoise(
        _num(ctx, v.get("position", 0.0), key + ".position", nonneg=True),
        _num(ctx, v.get("angle", 0.0), key + ".angle", nonneg=True),
    )


def _uncertainty(ctx: _Ctx, t: Mapping[str, Any], d: int = 2) -> Uncertainty:
    w = "[uncertainty] "
    _check_keys(ctx, t, TABLE_KEYS["[uncertainty]"] + (TABLE_KEYS["[uncertainty] 3-D"] if d == 3 else ()), w)
    px = _pair(ctx, t["port_x"], w + "port_x", ordered=True) if "port_x" in t else None
    py = _pair(ctx, t["port_y"], w + "port_y", ordered=True) if "port_y" in t else None
    pz = _pair(ctx, t["port_z"], w + "port_z", ordered=True) if "port_z" in t else None
    for axis, box in (("port_x", px), ("port_y", py), ("port_z", pz)):
        if box is not None:
            _metres(ctx, box, w + axis, list(box))
    tl = _pair(ctx, t["tip_force_over_ei"], w + "tip_force_over_ei", ordered=True) if "tip_force_over_ei" in t else None
    sn = _noise(ctx, t["sensor_noise"], w + "sensor_noise") if "sensor_noise" in t else None
    samples = t.get("samples", 5)
    if isinstance(samples, bool) or not isinstance(samples, int) or not 2 <= samples <= 41:
        raise ctx.fail(w + "samples", samples, "an integer from 2 to 41")
    if d == 3 and tl is not None and tl[0] < 0:
        raise ctx.fail(w + "tip_force_over_ei", list(tl),
                       "[lo, hi] with 0 <= lo <= hi: a lateral load magnitude (1/m^2), any direction normal to the shaft")
    return Uncertainty(py, pz, tl, sn, samples, px)


def _sensors(ctx: _Ctx, t: Mapping[str, Any]) -> Sensors:
    w = "[sensors] "
    _check_keys(ctx, t, TABLE_KEYS["[sensors]"], w)
    st = _num(ctx, t["step_time"], w + "step_time", positive=True) if "step_time" in t else None
    jit = _num(ctx, t.get("step_jitter", 0.0), w + "step_jitter", nonneg=True)
    if jit >= 1:
        raise ctx.fail(w + "step_jitter", t["step_jitter"], "a relative jitter from 0 to below 1 (a step's duration "
                       "stays > 0)")
    if "step_jitter" in t and st is None:
        raise ctx.fail(w + "step_jitter", t["step_jitter"], "step_time beside it (the jitter of which step?)")
    rates = {}
    for k in ("dropout_rate", "outlier_rate"):
        rates[k] = _num(ctx, t.get(k, 0.0), w + k, nonneg=True)
        if rates[k] >= 0.5:
            raise ctx.fail(w + k, t[k], "a share of rows from 0 to below 0.5")
    burst = t.get("dropout_burst", 1)
    if isinstance(burst, bool) or not isinstance(burst, int) or not 1 <= burst <= 1000:
        raise ctx.fail(w + "dropout_burst", burst, "an integer from 1 to 1000 (the longest burst, rows)")
    size = _pair(ctx, t["outlier_size"], w + "outlier_size", ordered=True) if "outlier_size" in t else (0.003, 0.010)
    if not size[0] > 0:
        raise ctx.fail(w + "outlier_size", t["outlier_size"], "[lo, hi] with 0 < lo <= hi (m)")
    return Sensors(
        _num(ctx, t.get("tracker_sigma", 0.0002), w + "tracker_sigma", nonneg=True),
        _num(ctx, t.get("encoder_sigma", 0.0), w + "encoder_sigma", nonneg=True),
        st, jit, rates["dropout_rate"], burst, rates["outlier_rate"], size,
    )


def _check_latency(ctx: _Ctx, effects: Mapping[str, Mapping[str, float]], sensors: Sensors) -> None:
    """``[effects.tracker_latency] tau``: 0 <= tau <= 5 steps (s with ``[sensors] step_time``, else steps)."""
    if "tracker_latency" not in effects:
        return
    tau = effects["tracker_latency"]["tau"]
    step = sensors.step_time
    top = 5.0 * (step if step is not None else 1.0)
    if not 0.0 <= tau <= top:
        unit = f"s: 5 steps of [sensors] step_time = {step:g} s" if step is not None else "steps without [sensors] step_time"
        raise ctx.fail("[effects.tracker_latency] tau", tau, f"a latency from 0 to {top:g} ({unit})")


def _fields(ctx: _Ctx, t: Mapping[str, Any], d: int = 2) -> Fields:
    w = "[fields] "
    _check_keys(ctx, t, TABLE_KEYS["[fields]"], w)
    r = _num(ctx, t.get("resolution", 0.002 if d == 2 else 0.004), w + "resolution", positive=True)
    if not 1e-4 <= r <= 0.05:
        raise ctx.fail(w + "resolution", r, "a grid spacing between 0.0001 and 0.05 m")
    region = _region(ctx, t["region"], w + "region", d) if "region" in t else None
    return Fields(r, region)


def _planner(ctx: _Ctx, t: Mapping[str, Any]) -> Planner:
    w = "[planner] "
    _check_keys(ctx, t, TABLE_KEYS["[planner]"], w)
    d = Planner()
    metric = t.get("metric", d.metric)
    if metric not in METRICS:
        raise ctx.fail(w + "metric", metric, " | ".join(f'"{m}"' for m in METRICS))
    planner = t.get("planner", d.planner)
    if not isinstance(planner, str) or not planner:
        raise ctx.fail(w + "planner", planner, "a planner name such as \"RRTstar\"")
    seed = t.get("seed", d.seed)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ctx.fail(w + "seed", seed, "an integer >= 0")
    cert = t.get("certifiable", d.certifiable)
    if not isinstance(cert, bool):
        raise ctx.fail(w + "certifiable", cert, "true or false")
    margin = _num(ctx, t.get("certify_margin", d.certify_margin), w + "certify_margin", nonneg=True)
    if margin >= 1:
        raise ctx.fail(w + "certify_margin", margin, "a number in [0, 1)")
    iterations = t.get("iterations", d.iterations)
    if iterations is not None and (isinstance(iterations, bool) or not isinstance(iterations, int)
                                   or not 1 <= iterations <= MAX_ITERATIONS):
        raise ctx.fail(w + "iterations", iterations,
                       f"an integer from 1 to {MAX_ITERATIONS}: the search's budget per query")
    return Planner(
        metric=metric,
        weight=_num(ctx, t.get("weight", d.weight), w + "weight", nonneg=True),
        planner=planner,
        time=_num(ctx, t["time"], w + "time", positive=True) if "time" in t else None,
        seed=seed,
        certifiable=cert,
        certify_margin=margin,
        iterations=iterations,
    )


def _queries(ctx: _Ctx, v: Any, d: int = 2) -> tuple[Query, ...]:
    if not isinstance(v, list):
        raise ctx.fail("[[query]]", v, "an array of tables")
    out = []
    names = set()
    for i, q in enumerate(v):
        w = f"[[query]][{i}] "
        if not isinstance(q, dict):
            raise ctx.fail(w.strip(), q, "a table")
        _check_keys(ctx, q, TABLE_KEYS["[[query]]"], w)
        name = q.get("name", f"query{i}")
        if not isinstance(name, str) or not name:
            raise ctx.fail(w + "name", name, "a non-empty string")
        if name in names:
            raise ctx.fail(w + "name", name, "a name used by no other query")
        names.add(name)
        ends = [_vec(ctx, _get(ctx, q, what, w), w + what, d) for what in ("start", "goal")]
        for what, p in zip(("start", "goal"), ends):
            _metres(ctx, p, w + what, list(p))
        out.append(Query(name, *ends))
    return tuple(out)


#: ``[[tolerance]]`` keys per ``kind`` (besides ``name`` and ``kind``; ``port_x`` only in 3-D).
TOLERANCE_KEYS: dict[str, tuple[str, ...]] = {
    "port": ("direction", "region", "gain", "tip_force_over_ei", "spacing"),
    "insertion_band": ("sensor_noise", "tip_force_over_ei", "gain", "samples", "length", "noise_sampling",
                       "draws", "seed", "hold", "shaft_angle"),
    "tip_load": ("region", "gain", "port_x", "port_y", "port_z", "spacing"),
    "tracker_noise": ("band", "tip_force_over_ei", "gain", "angle_ratio", "length", "samples", "hold",
                      "shaft_angle"),
    "port_placement": ("candidates", "spacing", "region", "resolution", "gain", "certify_margin", "refine",
                       "refine_levels"),
    # a scenario with several instruments (SETUP_TOLERANCE_KINDS)
    "triad_placement": ("instruments", "candidates", "spacing", "region", "resolution", "port_spacing",
                        "manipulation_angle", "manipulation_tolerance", "azimuth_tolerance", "coverage_weight",
                        "certify_margin", "gain"),
    "setup_placement": ("instruments", "bases", "candidates", "spacing", "region", "resolution", "port_spacing",
                        "manipulation_angle", "manipulation_tolerance", "azimuth_tolerance", "coverage_weight",
                        "certify_margin", "gain"),
}
_TOL_PLANAR = ("insertion_band", "tracker_noise")  # P2's flexion controller at insertion depths
#: their keys without a 3-D meaning yet: the hold variants, Monte Carlo noise, the planar shaft angle
_TOL_PLANAR_ONLY = ("hold", "noise_sampling", "draws", "seed", "shaft_angle")
_TOL_HOLDS = ("tip_force", "port_force", "port_deflection")


def _tol_int(ctx: _Ctx, t: Mapping[str, Any], key: str, w: str, lo: int, hi: int) -> int:
    s = t[key]
    if isinstance(s, bool) or not isinstance(s, int) or not lo <= s <= hi:
        raise ctx.fail(w + key, s, f"an integer from {lo} to {hi}")
    return s


def _shaft_direction(ctx: _Ctx, v: Any, key: str) -> tuple[float, float, float]:
    """A non-zero 3-vector: the port->tip direction of P2's insertion-depth queries in 3-D."""
    if not isinstance(v, list) or len(v) != 3:
        raise ctx.fail(key, v, "[x, y, z]: the port->tip direction, a non-zero 3-vector")
    vals = tuple(_num(ctx, x, key) for x in v)
    if not any(vals):
        raise ctx.fail(key, v, "[x, y, z]: the port->tip direction, a non-zero 3-vector")
    return vals


def _tolerances(ctx: _Ctx, v: Any, controller_gain: float, d: int = 2) -> tuple[Tolerance, ...]:
    """``[[tolerance]]`` tables (docs/interfaces.md; every key in docs/tolerance.md). Regions and
    candidate boxes have the scenario's axes (``x`` too in 3-D); ``insertion_band`` and
    ``tracker_noise`` take ``shaft_direction`` instead of ``shaft_angle`` in 3-D (and no ``hold`` or
    Monte Carlo keys there)."""
    if not isinstance(v, list):
        raise ctx.fail("[[tolerance]]", v, "an array of tables")
    out = []
    names: set[str] = set()
    for i, t in enumerate(v):
        w = f"[[tolerance]][{i}] "
        if not isinstance(t, dict):
            raise ctx.fail(w.strip(), t, "a table")
        kind = _get(ctx, t, "kind", w)
        if kind not in TOLERANCE_KINDS:
            raise ctx.fail(w + "kind", kind, " | ".join(f'"{k}"' for k in TOLERANCE_KINDS))
        allowed = tuple(k for k in TOLERANCE_KEYS[kind] if d == 3 or k != "port_x")
        if d == 3 and kind in _TOL_PLANAR:  # P2's controller in 3-D: a shaft direction, not an angle
            allowed = tuple(k for k in allowed if k not in _TOL_PLANAR_ONLY) + ("shaft_direction",)
        _check_keys(ctx, t, TABLE_KEYS["[[tolerance]]"] + allowed, w)
        name = _unique_name(ctx, t, w, f"tolerance{i}", names, "[[tolerance]]")
        opts: dict[str, Any] = {}
        opts["gain"] = _num(ctx, t.get("gain", controller_gain), w + "gain", positive=True)
        form = "{ " + ", ".join(f"{a} = [lo, hi]" for a in AXES[d]) + " }"
        if "region" in t:
            opts["region"] = _region(ctx, t["region"], w + "region", d)
        elif kind in ("port", "tip_load", "port_placement"):
            raise ctx.fail(w + "region", None, form + " (missing)")
        if kind == "port_placement":
            if "candidates" not in t:
                raise ctx.fail(w + "candidates", None, form + ": the box of nominal port positions to try (missing)")
            if t["candidates"] == "body_wall":  # ports on [anatomy.body_wall] (checked with the anatomy)
                if d != 3:
                    raise ctx.fail(w + "candidates", "body_wall", form + ' (candidates = "body_wall" needs a '
                                   "spatial scenario with [anatomy.body_wall])")
                opts["candidates"] = "body_wall"
            else:
                opts["candidates"] = _region(ctx, t["candidates"], w + "candidates", d)
            if "spacing" not in t:
                raise ctx.fail(w + "spacing", None, "the candidate grid spacing > 0 m (missing)")
            opts["spacing"] = _num(ctx, t["spacing"], w + "spacing", positive=True)
            if "resolution" in t:
                opts["resolution"] = _num(ctx, t["resolution"], w + "resolution", positive=True)
            if "certify_margin" in t:
                opts["certify_margin"] = _num(ctx, t["certify_margin"], w + "certify_margin", nonneg=True)
                if opts["certify_margin"] >= 1:
                    raise ctx.fail(w + "certify_margin", t["certify_margin"], "a number in [0, 1)")
            if "refine" in t:
                if not isinstance(t["refine"], bool):
                    raise ctx.fail(w + "refine", t["refine"], "true or false")
                opts["refine"] = t["refine"]
            if "refine_levels" in t:
                opts["refine_levels"] = _tol_int(ctx, t, "refine_levels", w, 0, 12)
        if kind == "port":
            dirs = ("x", "y", "z", "radial") if d == 3 else ("y", "z", "radial")
            dd = t.get("direction", "radial")
            if dd not in dirs:
                raise ctx.fail(w + "direction", dd, " | ".join(f'"{a}"' for a in dirs)
                               + (' ("x" only in a spatial scenario)' if dd == "x" else ""))
            opts["direction"] = dd
        if "sensor_noise" in t:
            opts["sensor_noise"] = _noise(ctx, t["sensor_noise"], w + "sensor_noise")
        elif kind == "insertion_band":
            raise ctx.fail(w + "sensor_noise", None, "{ position = m, angle = rad } (missing)")
        if "tip_force_over_ei" in t:
            tl = t["tip_force_over_ei"]
            if kind == "port" and isinstance(tl, list):
                opts["tip_force_over_ei"] = _pair(ctx, tl, w + "tip_force_over_ei", ordered=True)
            else:
                opts["tip_force_over_ei"] = _num(ctx, tl, w + "tip_force_over_ei")
            tls = opts["tip_force_over_ei"]
            if d == 3 and min(tls if isinstance(tls, tuple) else (tls,)) < 0:
                raise ctx.fail(w + "tip_force_over_ei", tl, "a lateral load magnitude >= 0 (1/m^2; a number or "
                               "[lo, hi] with 0 <= lo <= hi) in a spatial scenario")
        if kind in ("insertion_band", "tracker_noise"):
            if opts.get("tip_force_over_ei", 0.0) == 0.0:
                raise ctx.fail(w + "tip_force_over_ei", t.get("tip_force_over_ei"),
                               "a non-zero tip load Ft/EI (1/m^2): P2's flexion controller needs flexion")
        for key in ("port_x", "port_y", "port_z", "band"):
            if key in t:
                opts[key] = _pair(ctx, t[key], w + key, ordered=True)
        if "shaft_direction" in t:
            opts["shaft_direction"] = _shaft_direction(ctx, t["shaft_direction"], w + "shaft_direction")
        if "band" in opts and not 0.0 < opts["band"][0] <= opts["band"][1] < 1.0:
            raise ctx.fail(w + "band", list(opts["band"]), "insertion depths [lo, hi] with 0 < lo <= hi < 1 (r/L)")
        if "angle_ratio" in t:
            opts["angle_ratio"] = _num(ctx, t["angle_ratio"], w + "angle_ratio", nonneg=True)
        if "length" in t:
            opts["length"] = _num(ctx, t["length"], w + "length", positive=True)
        if "spacing" in t and kind != "port_placement":
            opts["spacing"] = _num(ctx, t["spacing"], w + "spacing", positive=True)
            if opts["spacing"] < 1e-5:
                raise ctx.fail(w + "spacing", t["spacing"], "a tip-grid spacing >= 0.00001 m")
        if "shaft_angle" in t:
            opts["shaft_angle"] = _num(ctx, t["shaft_angle"], w + "shaft_angle")
        if "hold" in t:
            if t["hold"] not in _TOL_HOLDS:
                raise ctx.fail(w + "hold", t["hold"], " | ".join(f'"{h}"' for h in _TOL_HOLDS))
            opts["hold"] = t["hold"]
        if "noise_sampling" in t:
            if t["noise_sampling"] not in ("worst", "random"):
                raise ctx.fail(w + "noise_sampling", t["noise_sampling"], '"worst" | "random"')
            opts["noise_sampling"] = t["noise_sampling"]
        if "samples" in t:
            opts["samples"] = _tol_int(ctx, t, "samples", w, 5 if kind == "insertion_band" else 2, 5001)
        if "draws" in t:
            opts["draws"] = _tol_int(ctx, t, "draws", w, 1, 1_000_000)
        if "seed" in t:
            opts["seed"] = _tol_int(ctx, t, "seed", w, 0, 2**32 - 1)
        if kind == "tracker_noise" and "band" not in opts:
            raise ctx.fail(w + "band", None, "[lo, hi] insertion band r/L that must stay monotonic (missing)")
        out.append(Tolerance(name, kind, opts))
    return tuple(out)


def _effects(ctx: _Ctx, t: Mapping[str, Any], d: int = 2, n_joints: int = 2) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for name, params in t.items():
        if name not in EFFECT_PARAMS:
            raise ctx.fail(f"[effects.{name}]", params, f"an effect of docs/physics.md: {', '.join(EFFECT_PARAMS)}")
        if not isinstance(params, dict):
            raise ctx.fail(f"[effects.{name}]", params, "a table of parameters")
        if EFFECT_DIMS.get(name, d) != d:
            raise ctx.fail(f"[effects.{name}]", params, "an effect of " + ("URDF arms (the planar arm has link_length)"
                                                                          if name == "joint_geometry" else
                                                                          "the planar arm (a URDF arm has joint_geometry)"))
        names = effect_params(name, d, n_joints)
        _check_keys(ctx, params, names, f"[effects.{name}] ")
        out[name] = {p: _num(ctx, params.get(p, 0.0), f"[effects.{name}] {p}") for p in names}
    return out


def _mesh_keys(ctx: _Ctx, t: Mapping[str, Any], w: str, base_dir: Path) -> dict[str, Any]:
    """``file`` (resolved against the scenario's folder; must exist, STL/OBJ/PLY), ``scale``,
    ``position``, ``rpy`` of a mesh obstacle or wall. The file's content is read by errplan.anatomy."""
    f = _get(ctx, t, "file", w)
    if not isinstance(f, str) or not f:
        raise ctx.fail(w + "file", f, "the path of an STL, OBJ or PLY file (relative to the scenario file)")
    path = (base_dir / f).resolve()
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ctx.fail(w + "file", f, "an STL, OBJ or PLY file (.stl, .obj, .ply)")
    if not path.is_file():
        raise ctx.fail(w + "file", f, f"an existing mesh file (missing: {path})")
    return {"file": str(path), "scale": _num(ctx, t.get("scale", 1.0), w + "scale", positive=True),
            "position": _vec(ctx, t.get("position", [0.0, 0.0, 0.0]), w + "position", 3),
            "rpy": _vec(ctx, t.get("rpy", [0.0, 0.0, 0.0]), w + "rpy", 3)}


def _anatomy(ctx: _Ctx, t: Mapping[str, Any], base_dir: Path) -> Anatomy:
    """``[anatomy]`` (docs/interfaces.md "Anatomy (spatial)"): numbers checked here (finite, radii and
    clearance >= 0 / > 0, files present); mesh contents and the geometry against the robot's port in
    :mod:`errplan.anatomy`."""
    w = "[anatomy] "
    _check_keys(ctx, t, TABLE_KEYS["[anatomy]"], w)
    clearance = _num(ctx, t.get("clearance", 0.0), w + "clearance", nonneg=True)
    obs = t.get("obstacle", [])
    if not isinstance(obs, list):
        raise ctx.fail("[[anatomy.obstacle]]", obs, "an array of tables")
    out, names = [], set()
    for i, o in enumerate(obs):
        wo = f"[[anatomy.obstacle]][{i}] "
        if not isinstance(o, dict):
            raise ctx.fail(wo.strip(), o, "a table")
        shape = _get(ctx, o, "shape", wo)
        if shape not in OBSTACLE_SHAPES:
            raise ctx.fail(wo + "shape", shape, " | ".join(f'"{x}"' for x in OBSTACLE_SHAPES))
        keys = OBSTACLE_KEYS[shape]
        _check_keys(ctx, o, TABLE_KEYS["[[anatomy.obstacle]]"] + keys, wo)
        name = _unique_name(ctx, o, wo, f"obstacle{i}", names, "obstacle")
        kw: dict[str, Any] = {}
        if shape == "mesh":
            kw = _mesh_keys(ctx, o, wo, base_dir)
        else:
            for k in ("center", "a", "b", "half_extents"):
                if k in keys:
                    kw[k] = _vec(ctx, _get(ctx, o, k, wo), wo + k, 3)
            if "radius" in keys:
                kw["radius"] = _num(ctx, _get(ctx, o, "radius", wo), wo + "radius", positive=True)
            if shape == "box":
                kw["rpy"] = _vec(ctx, o.get("rpy", [0.0, 0.0, 0.0]), wo + "rpy", 3)
                if min(kw["half_extents"]) <= 0:
                    raise ctx.fail(wo + "half_extents", list(kw["half_extents"]), "three half-lengths > 0 (m)")
        out.append(Obstacle(name=name, shape=shape, **kw))
    wall = None
    if "body_wall" in t:
        bw = t["body_wall"]
        ww = "[anatomy.body_wall] "
        if not isinstance(bw, dict):
            raise ctx.fail(ww.strip(), bw, "a table")
        shape = _get(ctx, bw, "shape", ww)
        if shape not in WALL_SHAPES:
            raise ctx.fail(ww + "shape", shape, " | ".join(f'"{x}"' for x in WALL_SHAPES))
        if shape == "ellipsoid":
            _check_keys(ctx, bw, TABLE_KEYS["[anatomy.body_wall] ellipsoid"], ww)
            radii = _vec(ctx, _get(ctx, bw, "radii", ww), ww + "radii", 3)
            if min(radii) <= 0:
                raise ctx.fail(ww + "radii", list(radii), "three semi-axes > 0 (m)")
            wall = BodyWall("ellipsoid", center=_vec(ctx, _get(ctx, bw, "center", ww), ww + "center", 3), radii=radii)
        else:
            _check_keys(ctx, bw, TABLE_KEYS["[anatomy.body_wall] mesh"], ww)
            wall = BodyWall("mesh", **_mesh_keys(ctx, bw, ww, base_dir))
    return Anatomy(clearance, tuple(out), wall)


_TOP = TABLE_KEYS[""]


def scenario_from_dict(doc: Mapping[str, Any], source: str = "<memory>") -> Scenario:
    """Validate a parsed TOML document into a :class:`Scenario` (see interfaces.md).

    A scenario is spatial (``dim == 3``) when its ``[robot]`` names a ``urdf``; every point then has
    three coordinates ``[x, y, z]``. Relative paths resolve against the scenario file's folder.
    """
    ctx = _Ctx(source)
    _check_keys(ctx, doc, _TOP, "")
    name = doc.get("name", Path(source).stem)
    if not isinstance(name, str) or not name:
        raise ctx.fail("name", name, "a non-empty string")
    desc = doc.get("description", "")
    if not isinstance(desc, str):
        raise ctx.fail("description", desc, "a string")
    controller = _controller(ctx, _table(ctx, doc, "controller", False))
    robot_t = _table(ctx, doc, "robot", False)
    base_dir = Path(source).resolve().parent if source != "<memory>" else Path.cwd()
    if "urdf" in robot_t:
        d = 3
        robot: Robot | UrdfRobot = _urdf_robot(ctx, robot_t, base_dir)
    else:
        d = 2
        robot = _robot(ctx, robot_t)
    n_joints = len(robot.joints) if d == 3 else 2
    anatomy = None
    if "anatomy" in doc:
        if d != 3:
            raise ctx.fail("[anatomy]", doc["anatomy"], "no [anatomy] in a planar scenario (anatomy is spatial: "
                           "a [robot] urdf)")
        anatomy = _anatomy(ctx, _table(ctx, doc, "anatomy", True), base_dir)
    sc = Scenario(
        name=name,
        description=desc,
        robot=robot,
        instrument=_instrument(ctx, _table(ctx, doc, "instrument", True)),
        port=_port(ctx, _table(ctx, doc, "port", True), d),
        controller=controller,
        uncertainty=_uncertainty(ctx, _table(ctx, doc, "uncertainty", False), d),
        sensors=_sensors(ctx, _table(ctx, doc, "sensors", False)),
        fields=_fields(ctx, _table(ctx, doc, "fields", False), d),
        planner=_planner(ctx, _table(ctx, doc, "planner", False)),
        queries=_queries(ctx, doc.get("query", []), d),
        tolerances=_tolerances(ctx, doc.get("tolerance", []), controller.gain, d),
        effects=_effects(ctx, _table(ctx, doc, "effects", False), d, n_joints),
        source=source,
        anatomy=anatomy,
    )
    _check_latency(ctx, sc.effects, sc.sensors)
    for i, tol in enumerate(sc.tolerances):
        if tol.get("candidates") == "body_wall" and (anatomy is None or anatomy.body_wall is None):
            raise ctx.fail(f"[[tolerance]][{i}] candidates", "body_wall", "a box of candidate ports, or \"body_wall\" "
                           "with an [anatomy.body_wall] table (missing)")
    return sc


def read_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file (the data only; :func:`errplan.load_scenario` also checks it
    against the robot)."""
    from .inputs import read_text  # missing, directory, binary, not UTF-8, too large: one ScenarioError

    p = Path(path)
    text = read_text(p, "scenario file")
    try:
        doc = tomllib.loads(text)
    except (ValueError, RecursionError) as e:  # TOMLDecodeError is a ValueError; absurd nesting recurses
        raise ScenarioError(f"{p}: not valid TOML: {e}") from None
    if "arm" in doc:  # several instruments: one arm at a time (read_setup reads them all)
        return setup_from_dict(doc, str(p)).arm(None)
    return scenario_from_dict(doc, str(p))


# ----------------------------------------------------------------------------- several arms
@dataclass(frozen=True)
class Endoscope:
    """``[endoscope]`` (docs/interfaces.md "Several instruments and the endoscope"): a straight rigid
    shaft through ``port`` (estimate, truth) whose optical axis runs toward ``look_at``; the lens sits
    ``insertion`` (m) along it from the port, sees a cone of full angle ``fov`` (rad) between the
    depths ``depth`` = (near, far) (m from the lens). ``uncertainty``: the port box (port_x/y/z)."""

    port: Port
    look_at: tuple[float, float, float]
    insertion: float
    fov: float
    depth: tuple[float, float]
    uncertainty: Uncertainty = Uncertainty()
    keep_visible: bool = False


@dataclass(frozen=True)
class Setup:
    """A scenario file read once: one :class:`Scenario` per instrument arm (the same type every command
    takes, with the shared ``[anatomy]``, ``[fields]``, ``[planner]``, ``[sensors]`` and ``[effects]``
    tables and that arm's queries), the endoscope and the setup's clearances. A one-instrument file is
    the one-arm case (``several`` false, its arm named ``"arm"``, no endoscope).

    ``rests``: per arm, the tip's rest point (None in a one-instrument file); ``triads``: the
    ``triad_placement`` tolerance queries (options as parsed)."""

    name: str
    source: str
    arm_names: tuple[str, ...]
    arms: tuple[Scenario, ...]
    rests: tuple[tuple[float, float, float] | None, ...] = ()
    endoscope: Endoscope | None = None
    shaft_clearance: float = 0.0
    arm_clearance: float | None = None
    triads: tuple[Tolerance, ...] = ()
    several: bool = False
    #: ``[setup] patient_clearance`` (m): every arm link from the body solid (``setup_placement``); None: no check
    patient_clearance: float | None = None

    @property
    def dim(self) -> int:
        """The dimension of its arms (3 for several arms: URDF arms; a one-instrument file: its scenario's)."""
        return self.arms[0].dim

    def arm(self, name: str | None, option: str = "--arm") -> Scenario:
        """The scenario of arm ``name`` (None: the only arm). One :class:`ScenarioError` otherwise."""
        if name is None:
            if len(self.arms) == 1:
                return self.arms[0]
            raise ScenarioError(f"{self.source}: the scenario has {len(self.arms)} arms ({', '.join(self.arm_names)}): "
                                f"name one with {option} NAME")
        if name not in self.arm_names:
            if not self.several:
                raise ScenarioError(f"{option} {name}: {self.source} has one instrument and no [[arm]] tables")
            raise ScenarioError(f"{option} {name}: expected one of the arms {', '.join(self.arm_names)}")
        return self.arms[self.arm_names.index(name)]

    def rest(self, name: str):
        return self.rests[self.arm_names.index(name)]

    def held_shafts(self, name: str) -> tuple[Obstacle, ...]:
        """What arm ``name`` sees while it moves: every other instrument's shaft held at its rest point,
        conv(box_j ∪ {rest_j}), and the endoscope's, conv(box_e ∪ {lens}), as obstacles of shape
        ``"shaft"`` (box centre and half extents, tip ``a``). Their ``radius`` is ``[setup] shaft_clearance -
        [anatomy] clearance`` (possibly negative): the anatomy's check "distance - radius >= clearance" is
        then exactly "distance >= shaft_clearance"."""
        an = self.arms[0].anatomy
        adj = self.shaft_clearance - (an.clearance if an is not None else 0.0)
        out = []
        for n, sc, rest in zip(self.arm_names, self.arms, self.rests):
            if n != name and rest is not None:
                c, h = _box_of(sc.port.estimate, sc.uncertainty)
                out.append(Obstacle(name=f"{n} shaft (held)", shape="shaft", center=c, half_extents=h, a=rest,
                                    radius=adj))
        e = self.endoscope
        if e is not None:
            c, h = _box_of(e.port.estimate, e.uncertainty)
            u = [b - a for a, b in zip(e.port.estimate, e.look_at)]
            nu = math.sqrt(sum(x * x for x in u))
            lens = tuple(p + e.insertion * x / nu for p, x in zip(e.port.estimate, u))
            out.append(Obstacle(name="endoscope shaft", shape="shaft", center=c, half_extents=h, a=lens, radius=adj))
        return tuple(out)

    def moving(self, name: str | None) -> Scenario:
        """The scenario of arm ``name`` as it moves among the others (:meth:`held_shafts` join its
        anatomy's obstacles: fields, plans, certificates and replays keep them clear as any obstacle).
        The one-arm case: the arm's scenario unchanged."""
        sc = self.arm(name)
        if not self.several:
            return sc
        held = self.held_shafts(self.arm_names[self.arms.index(sc)])
        an = sc.anatomy or Anatomy()
        view = self.endoscope if (self.endoscope is not None and self.endoscope.keep_visible) else None
        arms = None
        if self.arm_clearance is not None:  # [setup] arm_clearance: the others' links, held at rest
            me = self.arm_names[self.arms.index(sc)]
            arms = HeldArms(float(self.arm_clearance),
                            tuple((n, o.robot, tuple(o.port.estimate), float(o.instrument.length), tuple(rest))
                                  for n, o, rest in zip(self.arm_names, self.arms, self.rests)
                                  if n != me and rest is not None), self.rest(me))
        return sc.with_(anatomy=replace(an, obstacles=an.obstacles + held), view=view, held_arms=arms)


@dataclass(frozen=True)
class HeldArms:
    """What the moving arm's links keep clear of ([setup] arm_clearance, :meth:`Setup.moving`): the
    ``clearance`` (m), per other arm ``(name, robot, port estimate, shaft length, rest tip)``, and the
    moving arm's own rest tip (its configuration there picks the branch of its inverse kinematics); the
    arm-check model is built from it once per plan (:mod:`errplan.planning.arm_checks`)."""

    clearance: float
    arms: tuple = ()
    rest: tuple | None = None


#: the tables each ``[[arm]]`` holds (a one-instrument scenario has them at the top)
ARM_TABLES = tuple(k for k in TABLE_KEYS["[[arm]]"] if k not in ("name", "rest"))
_TRIAD_KEYS = TABLE_KEYS["[[tolerance]]"] + TOLERANCE_KEYS["triad_placement"]
_SETUP_KEYS = TABLE_KEYS["[[tolerance]]"] + TOLERANCE_KEYS["setup_placement"]
# a setup_placement's base candidates: a pose of a list, or a grid on a horizontal rectangle times yaws
_BASE_POSE_KEYS = ("position", "rpy")
_BASE_GRID_KEYS = ("y", "x", "z", "spacing", "yaw")


def _box_of(estimate, un: Uncertainty) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Centre and half extents of the port box ``estimate`` + [port_x] x [port_y] x [port_z]."""
    c, h = [], []
    for e, ax in zip(estimate, "xyz"):
        lo, hi = getattr(un, f"port_{ax}", None) or (0.0, 0.0)
        c.append(float(e) + (lo + hi) / 2)
        h.append((hi - lo) / 2)
    return tuple(c), tuple(h)


def _endoscope(ctx: _Ctx, t: Any) -> Endoscope:
    w = "[endoscope] "
    if not isinstance(t, dict):
        raise ctx.fail("[endoscope]", _Short(_short(t)), "a table")
    _check_keys(ctx, t, TABLE_KEYS["[endoscope]"], w)
    pt = _get(ctx, t, "port", w)
    if not isinstance(pt, dict):
        raise ctx.fail(w + "port", _Short(_short(pt)), "{ estimate = [x, y, z], position = [x, y, z] }")
    _check_keys(ctx, pt, TABLE_KEYS["[endoscope] port"], w + "port.")
    pos = _vec(ctx, _get(ctx, pt, "position", w + "port."), w + "port.position", 3)
    est = _vec(ctx, pt.get("estimate", list(pos)), w + "port.estimate", 3)
    look = _vec(ctx, _get(ctx, t, "look_at", w), w + "look_at", 3)
    if math.dist(look, est) < 1e-6:
        raise ctx.fail(w + "look_at", list(look), "a point away from the endoscope's port (the optical axis)")
    ins = _num(ctx, _get(ctx, t, "insertion", w), w + "insertion", positive=True)
    fov = _num(ctx, _get(ctx, t, "fov", w), w + "fov")
    if not 0 < fov < math.pi:
        raise ctx.fail(w + "fov", fov, "a full cone angle in (0, pi) rad")
    near, far = _pair(ctx, _get(ctx, t, "depth", w), w + "depth")
    if not 0 <= near < far:
        raise ctx.fail(w + "depth", [near, far], "[near, far] m from the lens with 0 <= near < far (increasing)")
    un = t.get("uncertainty", {})
    if not isinstance(un, dict):
        raise ctx.fail(w + "uncertainty", _Short(_short(un)), "{ port_x = [lo, hi], port_y = ..., port_z = ... }")
    _check_keys(ctx, un, TABLE_KEYS["[endoscope] uncertainty"], w + "uncertainty.")
    box = {k: _pair(ctx, un[k], w + f"uncertainty.{k}", ordered=True) for k in ("port_x", "port_y", "port_z")
           if k in un}
    kv = t.get("keep_visible", False)
    if not isinstance(kv, bool):
        raise ctx.fail(w + "keep_visible", kv, "true or false")
    return Endoscope(Port(pos, est), look, ins, fov, (near, far), Uncertainty(**box), kv)


def _triad(ctx: _Ctx, t: dict, i: int, arm_names: tuple[str, ...], margin: float) -> Tolerance:
    """A ``triad_placement`` or ``setup_placement`` query (docs/interfaces.md): options with their defaults
    filled in (a setup's ``bases`` as given: :func:`_setup_bases` reads them once the arms are read)."""
    w = f"[[tolerance]][{i}] "
    kind = t.get("kind")
    _check_keys(ctx, t, _SETUP_KEYS if kind == "setup_placement" else _TRIAD_KEYS, w)
    o: dict[str, Any] = {}
    ins = _get(ctx, t, "instruments", w, list(arm_names[:2]))
    if (not isinstance(ins, list) or len(ins) != 2 or len(set(map(str, ins))) != 2
            or not all(isinstance(x, str) and x in arm_names for x in ins)):
        raise ctx.fail(w + "instruments", ins, f"two different arms of the scenario ({', '.join(arm_names)})")
    o["instruments"] = tuple(ins)
    roles = tuple(ins) + ("endoscope",)
    cand = _get(ctx, t, "candidates", w)
    if cand == "body_wall":
        o["candidates"] = "body_wall"
    elif isinstance(cand, dict):
        _check_keys(ctx, cand, roles, w + "candidates.")
        out = {}
        for r in roles:
            pts = _get(ctx, cand, r, w + "candidates.")
            if not isinstance(pts, list) or not pts:
                raise ctx.fail(w + f"candidates.{r}", pts, "a non-empty list of points [x, y, z] on the body wall")
            out[r] = tuple(_vec(ctx, p, w + f"candidates.{r}[{j}]", 3) for j, p in enumerate(pts))
        o["candidates"] = out
    else:
        raise ctx.fail(w + "candidates", _Short(_short(cand)), '"body_wall" or { ' + ", ".join(
            f"{r} = [[x, y, z], ...]" for r in roles) + " }")
    o["spacing"] = _num(ctx, t.get("spacing", 0.03), w + "spacing", positive=True)
    o["region"] = _region(ctx, _get(ctx, t, "region", w), w + "region", 3)
    if "resolution" in t:
        o["resolution"] = _num(ctx, t["resolution"], w + "resolution", positive=True)
    o["port_spacing"] = _num(ctx, t.get("port_spacing", 0.06), w + "port_spacing", nonneg=True)
    o["manipulation_angle"] = _num(ctx, t.get("manipulation_angle", math.radians(60)), w + "manipulation_angle")
    if not 0 < o["manipulation_angle"] < math.pi:
        raise ctx.fail(w + "manipulation_angle", t["manipulation_angle"], "an angle in (0, pi) rad")
    for k in ("manipulation_tolerance", "azimuth_tolerance"):
        o[k] = _num(ctx, t.get(k, math.radians(15)), w + k, positive=True)
    o["coverage_weight"] = _num(ctx, t.get("coverage_weight", 10.0), w + "coverage_weight", nonneg=True)
    o["certify_margin"] = _num(ctx, t.get("certify_margin", margin), w + "certify_margin", nonneg=True)
    if o["certify_margin"] >= 1:
        raise ctx.fail(w + "certify_margin", t["certify_margin"], "a number in [0, 1)")
    if "gain" in t:
        o["gain"] = _num(ctx, t["gain"], w + "gain", positive=True)
    if kind == "setup_placement":
        b = t.get("bases", {})
        if not isinstance(b, dict):
            raise ctx.fail(w + "bases", _Short(_short(b)), "a table of base candidates per instrument arm "
                           "(bases.<arm> = [{ position, rpy }, ...] or { y, x, z, spacing, yaw })")
        _check_keys(ctx, b, tuple(ins), w + "bases.")
        o["bases"] = dict(b)
    return Tolerance(_get(ctx, t, "name", w, f"tolerance{i}"), kind, o)


def _rpy_of(R) -> tuple[float, float, float]:
    """URDF roll, pitch, yaw of a rotation matrix R = Rz(yaw) Ry(pitch) Rx(roll) (rows of 3)."""
    pitch = math.asin(max(-1.0, min(1.0, -R[2][0])))
    if abs(R[2][0]) < 1.0 - 1e-12:
        return math.atan2(R[2][1], R[2][2]), pitch, math.atan2(R[1][0], R[0][0])
    return 0.0, pitch, math.atan2(-R[0][1], R[1][1])  # gimbal lock: the roll folded into the yaw


def _rpy_rows(rpy) -> list[list[float]]:
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr]]


def grid_base_rpy(yaw: float, own_rpy) -> tuple[float, float, float]:
    """The rpy of a grid base: rotation R_y(yaw) R(own_rpy) (the yaw about the world's vertical y after the
    arm's own rpy; docs/interfaces.md "Setup placement")."""
    c, s = math.cos(yaw), math.sin(yaw)
    Ry = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    R0 = _rpy_rows(own_rpy)
    return _rpy_of([[sum(Ry[i][k] * R0[k][j] for k in range(3)) for j in range(3)] for i in range(3)])


def _axis(lo: float, hi: float, h: float) -> list[float]:
    """lo, lo + h, ... up to hi inclusive (within a millionth of h)."""
    n = int(math.floor((hi - lo) / h + 1e-6)) if hi >= lo else -1
    return [lo + k * h for k in range(n + 1)]


def _setup_bases(ctx: _Ctx, t: Tolerance, arms: Mapping[str, Scenario]) -> Tolerance:
    """A ``setup_placement`` query with its ``bases`` read: per instrument arm a tuple of ``(position,
    rpy)`` (an arm without ``bases.<arm>``: its own base only). A list of poses, or a grid (docs/interfaces.md)."""
    w = f"[[tolerance]] {t.name!r} bases."
    out = {}
    for name in t.options["instruments"]:
        own = arms[name].robot
        b = t.options["bases"].get(name)
        if b is None:
            out[name] = ((tuple(own.base_position), tuple(own.base_rpy)),)
            continue
        if isinstance(b, list):
            if not b:
                raise ctx.fail(w + name, b, "a non-empty list of base poses { position = [x, y, z], rpy = [r, p, y] }")
            poses = []
            for j, p in enumerate(b):
                if not isinstance(p, dict):
                    raise ctx.fail(f"{w}{name}[{j}]", _Short(_short(p)), "{ position = [x, y, z], rpy = [r, p, y] }")
                _check_keys(ctx, p, _BASE_POSE_KEYS, f"{w}{name}[{j}].")
                pos = _vec(ctx, _get(ctx, p, "position", f"{w}{name}[{j}]."), f"{w}{name}[{j}].position", 3)
                rpy = _vec(ctx, p.get("rpy", list(own.base_rpy)), f"{w}{name}[{j}].rpy", 3)
                poses.append((pos, rpy))
            out[name] = tuple(poses)
        elif isinstance(b, dict):
            _check_keys(ctx, b, _BASE_GRID_KEYS, f"{w}{name}.")
            y = _num(ctx, _get(ctx, b, "y", f"{w}{name}."), f"{w}{name}.y")
            xr = _pair(ctx, _get(ctx, b, "x", f"{w}{name}."), f"{w}{name}.x")
            zr = _pair(ctx, _get(ctx, b, "z", f"{w}{name}."), f"{w}{name}.z")
            h = _num(ctx, _get(ctx, b, "spacing", f"{w}{name}."), f"{w}{name}.spacing", positive=True)
            yaws = b.get("yaw", [0.0])
            if not isinstance(yaws, list):
                yaws = [yaws]
            yaws = [_num(ctx, v, f"{w}{name}.yaw") for v in yaws]
            for v in yaws:
                if not -math.pi <= v <= math.pi:
                    raise ctx.fail(f"{w}{name}.yaw", v, "angles in [-pi, pi] rad (about the vertical)")
            xs, zs = _axis(*xr, h), _axis(*zr, h)
            if not (xs and zs and yaws):
                raise ctx.fail(f"{w}{name}", _Short(_short(b)), "a grid with at least one point (x and z ranges "
                               "[lo, hi] with lo <= hi, at least one yaw)")
            rpys = [grid_base_rpy(v, own.base_rpy) for v in yaws]
            out[name] = tuple(((x, y, z), r) for x in xs for z in zs for r in rpys)
        else:
            raise ctx.fail(w + name, _Short(_short(b)), "a list of base poses [{ position, rpy }, ...] or a grid "
                           "{ y, x = [lo, hi], z = [lo, hi], spacing, yaw = [...] }")
    return replace(t, options=dict(t.options, bases=out))


def setup_from_dict(doc: Mapping[str, Any], source: str = "<memory>") -> Setup:
    """Validate a parsed TOML document into a :class:`Setup`: per ``[[arm]]`` a one-instrument
    :class:`Scenario` (:func:`scenario_from_dict` of the shared tables with that arm's tables and
    queries), or, without ``[[arm]]``, the one-arm setup of the document's one scenario."""
    ctx = _Ctx(source)
    if not isinstance(doc, dict) or "arm" not in doc:
        for key in ("endoscope", "setup"):
            if isinstance(doc, dict) and key in doc:
                raise ctx.fail(f"[{key}]", _Short(_short(doc[key])), "[[arm]] tables beside it (an endoscope and "
                               "setup clearances belong to a scenario with several instruments)")
        sc = scenario_from_dict(doc, source)
        return Setup(sc.name, source, ("arm",), (sc,), (None,))
    _check_keys(ctx, doc, _TOP + TABLE_KEYS["several instruments"], "")
    for key in ARM_TABLES:
        if key in doc:
            raise ctx.fail(f"[{key}]", _Short(_short(doc[key])), "no top-level instrument table beside [[arm]] "
                           f"(each arm holds its own [arm.{key}]; a scenario with both is ambiguous)")
    arms_t = doc["arm"]
    if not isinstance(arms_t, list) or not arms_t or not all(isinstance(a, dict) for a in arms_t):
        raise ctx.fail("[[arm]]", _Short(_short(arms_t)), "an array of tables, one per instrument arm")
    names: set[str] = set()
    arm_names = []
    for i, a in enumerate(arms_t):
        w = f"[[arm]][{i}] "
        _check_keys(ctx, a, TABLE_KEYS["[[arm]]"], w)
        arm_names.append(_unique_name(ctx, a, w, f"arm{i}", names, "[[arm]]"))
    arm_names_t = tuple(arm_names)
    name = doc.get("name", Path(source).stem)
    # queries: each names its arm (required with several arms)
    queries = doc.get("query", [])
    if not isinstance(queries, list):
        raise ctx.fail("[[query]]", _Short(_short(queries)), "an array of tables")
    q_arm: list[str] = []
    q_plain = []
    for i, q in enumerate(queries):
        w = f"[[query]][{i}] "
        if not isinstance(q, dict):
            raise ctx.fail(w.strip(), _Short(_short(q)), "a table")
        an = q.get("arm")
        if an is None and len(arm_names_t) > 1:
            raise ctx.fail(w + "arm", None, f"the arm that moves, one of {', '.join(arm_names_t)} (missing: required "
                           "when there are several arms)")
        an = arm_names_t[0] if an is None else an
        if an not in arm_names_t:
            raise ctx.fail(w + "arm", an, f"one of the arms {', '.join(arm_names_t)} (unknown arm)")
        q_arm.append(an)
        q_plain.append({k: v for k, v in q.items() if k != "arm"})
    _queries(ctx, q_plain, 3)  # names unique over the whole file, points checked with their index
    planner = _planner(ctx, _table(ctx, doc, "planner", False))
    tols = doc.get("tolerance", [])
    if not isinstance(tols, list):
        raise ctx.fail("[[tolerance]]", _Short(_short(tols)), "an array of tables")
    triads, per_arm = [], []
    for i, t in enumerate(tols):
        if isinstance(t, dict) and t.get("kind") in SETUP_TOLERANCE_KINDS:
            triads.append(_triad(ctx, t, i, arm_names_t, planner.certify_margin))
        else:
            per_arm.append(t)
    tnames = [t.name for t in triads] + [t.get("name") for t in per_arm if isinstance(t, dict)]
    dup = [n for n in tnames if n is not None and tnames.count(n) > 1]
    if dup:
        raise ctx.fail("[[tolerance]] name", dup[0], "a name used by no other [[tolerance]]")
    shared = {k: v for k, v in doc.items() if k not in ("arm", "endoscope", "setup", "query", "tolerance")}
    arms, rests = [], []
    for i, (an, a) in enumerate(zip(arm_names_t, arms_t)):
        sub = dict(shared, name=f"{name}.{an}", query=[q for q, qa in zip(q_plain, q_arm) if qa == an],
                   tolerance=per_arm)
        sub.update({k: a[k] for k in ARM_TABLES if k in a})
        robot = a.get("robot")
        if not isinstance(robot, dict) or "urdf" not in robot:
            raise ctx.fail(f"[[arm]][{i}] robot.urdf", None if not isinstance(robot, dict) else robot.get("urdf"),
                           "a URDF arm (several instruments are spatial: [arm.robot] urdf = ...)")
        try:
            sc = scenario_from_dict(sub, source)
        except ScenarioError as e:
            msg = str(e)
            head = f"{source}: "
            body = msg[len(head):] if msg.startswith(head) else msg
            if any(body.startswith(f"[{k}]") for k in ARM_TABLES):
                j = body.index("]")
                rest = body[j + 1:]
                body = f"[[arm]][{i}] (name {an!r}) {body[1:j]}" + (rest if rest.startswith(" = ") else "." + rest[1:])
            raise ScenarioError(head + body) from None
        arms.append(sc)
        rests.append(_vec(ctx, _get(ctx, a, "rest", f"[[arm]][{i}] "), f"[[arm]][{i}] rest", 3))
    endo = _endoscope(ctx, doc["endoscope"]) if "endoscope" in doc else None
    st = _table(ctx, doc, "setup", False)
    _check_keys(ctx, st, TABLE_KEYS["[setup]"], "[setup] ")
    shaft_c = _num(ctx, st.get("shaft_clearance", 0.0), "[setup] shaft_clearance", nonneg=True)
    arm_c = _num(ctx, st["arm_clearance"], "[setup] arm_clearance", positive=True) if "arm_clearance" in st else None
    patient_c = (_num(ctx, st["patient_clearance"], "[setup] patient_clearance", nonneg=True)
                 if "patient_clearance" in st else None)
    by_name = dict(zip(arm_names_t, arms))
    triads = [_setup_bases(ctx, t, by_name) if t.kind == "setup_placement" else t for t in triads]
    for i, t in enumerate(triads):
        if endo is None:
            raise ctx.fail(f"[[tolerance]] {t.name!r} kind", t.kind, "an [endoscope] table (missing)")
        if t.get("candidates") == "body_wall" and (arms[0].anatomy is None or arms[0].anatomy.body_wall is None):
            raise ctx.fail(f"[[tolerance]] {t.name!r} candidates", "body_wall", "an [anatomy.body_wall] table "
                           "(missing)")
    return Setup(name, source, arm_names_t, tuple(arms), tuple(rests), endo, shaft_c, arm_c, tuple(triads), True,
                 patient_clearance=patient_c)


def read_document(path: str | Path) -> dict:
    """A scenario file parsed as TOML (one :class:`ScenarioError` for a file that is not)."""
    from .inputs import read_text

    p = Path(path)
    text = read_text(p, "scenario file")
    try:
        return tomllib.loads(text)
    except (ValueError, RecursionError) as e:
        raise ScenarioError(f"{p}: not valid TOML: {e}") from None


def read_setup(path: str | Path) -> Setup:
    """Read and validate a scenario file with one or several arms (the data only; :func:`errplan.api.
    load_setup` also checks it against the robots and the anatomy)."""
    return setup_from_dict(read_document(path), str(Path(path)))
