"""MkDocs hooks of errplan's documentation site (``mkdocs.yml`` ``hooks:``).

- ``docs/reference/scenario.md`` is generated from the parser's own key tables
  (:data:`errplan.scenario.TABLE_KEYS`, :data:`~errplan.scenario.TOLERANCE_KEYS`,
  :data:`~errplan.scenario.OBSTACLE_KEYS`, :func:`~errplan.scenario.effect_params`) by running this file
  (``python docs/_hooks/errplan_docs.py``), and committed, so that it reads on disk and on the forge as
  well as on the site. It cannot drift from the code: the build fails when the committed page differs
  from what this file generates (as does ``tests/test_newcomer.py``), and a key the parser accepts
  without a description below, or a description of a key the parser does not accept, fails both.
- ``<!-- errplan-options: COMMAND -->`` in a page becomes the table of that command's options, read
  from the argparse parser of :mod:`errplan.cli` (flags, help text with units and defaults).
"""
from __future__ import annotations

import argparse
import re

from mkdocs.exceptions import PluginError

# ------------------------------------------------------------------ what each key means
# (table, key) -> description. Tables as in errplan.scenario.TABLE_KEYS; tolerance keys under
# "[[tolerance]] KIND" (or "[[tolerance]] *" for a meaning shared by every kind that accepts the key),
# obstacle keys under "[[anatomy.obstacle]] SHAPE".
KEY_DOCS: dict[tuple[str, str], str] = {
    ("", "name"): "the scenario's name, a non-empty string (default: the file's stem)",
    ("", "description"): "free text",
    ("", "robot"): "table `[robot]`: the arm (planar, or a URDF)",
    ("", "instrument"): "table `[instrument]`: the shaft",
    ("", "port"): "table `[port]`: the true port and the controller's estimate",
    ("", "controller"): "table `[controller]`: gain and Jacobian model",
    ("", "uncertainty"): "table `[uncertainty]` (optional): the bounded error set of the worst-case fields",
    ("", "sensors"): "table `[sensors]` (optional): noise of simulated measured data",
    ("", "fields"): "table `[fields]` (optional): the tip grid",
    ("", "planner"): "table `[planner]` (optional): cost metric and OMPL planner",
    ("", "query"): "array of tables `[[query]]`: start and goal tips to plan between",
    ("", "tolerance"): "array of tables `[[tolerance]]`: tolerance-design queries",
    ("", "effects"): "tables `[effects.NAME]` (optional): physical effects present in the truth",
    ("", "anatomy"): "table `[anatomy]` (optional, spatial only): obstacles and the body wall",
    ("[robot]", "base"): "shoulder position `[y, z]`, m (P1's `[0.210, -0.210]`)",
    ("[robot]", "link_lengths"): "`[l1, l2]`, m (P1's `[0.210, 0.210]`)",
    ("[robot]", "home_angles"): "`[h1, h2]`, rad: the home pose the joint angles count from (`[0, -π/2]`)",
    ("[robot]", "joint_limits"): "`[[lo, hi], [lo, hi]]`, rad (P1's `[[-1.9, 1.2], [-0.7, 1.0]]`)",
    ("[robot]", "joint_sum_limits"): "`[lo, hi]`, rad: limits on q1 + q2 (P1's `[-0.3, 2.8]`)",
    ("[robot] urdf", "urdf"): "the URDF file, relative to the scenario, or `package://NAME/PATH` (required; makes the scenario spatial)",
    ("[robot] urdf", "package_path"): "folders where `package://` URIs resolve, before `ROS_PACKAGE_PATH` and installed description packages",
    ("[robot] urdf", "joints"): "the actuated joints that place the wrist, root to wrist (required)",
    ("[robot] urdf", "wrist"): "the link whose origin is the instrument's pivot (required)",
    ("[robot] urdf", "base_position"): "the URDF root in the world frame `[x, y, z]`, m (`[0, 0, 0]`)",
    ("[robot] urdf", "base_rpy"): "the URDF root's orientation, rad, URDF roll-pitch-yaw (`[0, 0, 0]`)",
    ("[robot] urdf", "joint_limits"): "`[[lo, hi], ...]` per actuated joint, rad: overrides the URDF's limits",
    ("[robot] urdf", "fixed_joints"): "`{ joint = angle }`, rad: the chain's other joints (default 0)",
    ("[robot] urdf", "coupled_limits"): "array of linear limits on joint combinations (each a `[robot] coupled_limits` table)",
    ("[robot] coupled_limits", "joints"): "names of the actuated joints in the combination",
    ("[robot] coupled_limits", "coeffs"): "one coefficient per joint: the limit holds on Σ coeff·q",
    ("[robot] coupled_limits", "range"): "`[lo, hi]`, rad: the allowed range of the combination",
    ("[instrument]", "length"): "shaft length L, wrist pivot to tip, m",
    ("[instrument]", "flexural_rigidity"): "EI, N m² (optional)",
    ("[port]", "position"): "the true port, m (`[y, z]`, or `[x, y, z]` in 3-D)",
    ("[port]", "estimate"): "the port the controller believes, m",
    ("[controller]", "gain"): "controller gain k, > 0",
    ("[controller]", "jacobian"): '`"rigid"` (P1\'s lever) or `"flexion"` (P2\'s flexion controller)',
    ("[uncertainty]", "port_y"): "`[lo, hi]`, m: true port = estimate + offset along y",
    ("[uncertainty]", "port_z"): "`[lo, hi]`, m: the offset along z",
    ("[uncertainty]", "tip_force_over_ei"): "`[lo, hi]`, 1/m²: lateral tip load Ft/EI (in 3-D a magnitude ≥ 0, any direction normal to the shaft)",
    ("[uncertainty]", "sensor_noise"): "`{ position = m, angle = rad }`: bounds on each measured coordinate (flexion controller)",
    ("[uncertainty]", "samples"): "samples per uncertain axis before local refinement, 2 to 41 (5)",
    ("[uncertainty] 3-D", "port_x"): "`[lo, hi]`, m: the offset along x (spatial scenarios)",
    ("sensor_noise", "position"): "bound on each measured position coordinate, m (0)",
    ("sensor_noise", "angle"): "bound on each measured direction, rad (0)",
    ("[sensors]", "tracker_sigma"): "std of the tracked tip's noise in simulated data, m (0.0002)",
    ("[sensors]", "encoder_sigma"): "std of the joint encoders' noise in simulated data, rad (0)",
    ("[sensors]", "step_time"): "`errplan experiment`: write a `time` column, steps this long on average, s (none)",
    ("[sensors]", "step_jitter"): "`errplan experiment`: each step's duration uniform within ± this share of "
                                  "step_time (0)",
    ("[sensors]", "dropout_rate"): "`errplan experiment`: share of rows without a tracked tip, in bursts (0)",
    ("[sensors]", "dropout_burst"): "`errplan experiment`: longest dropout burst, rows; lengths uniform 1..burst (1)",
    ("[sensors]", "outlier_rate"): "`errplan experiment`: share of rows whose tracked tip is far off (0)",
    ("[sensors]", "outlier_size"): "`errplan experiment`: the outliers' distance [lo, hi], uniform, random "
                                   "direction, m ([0.003, 0.010])",
    ("[fields]", "resolution"): "tip-grid spacing, m, 1e-4 to 0.05 (0.002 planar, 0.004 spatial)",
    ("[fields]", "region"): "`{ y = [lo, hi], z = [lo, hi] }` (`x` too in 3-D), m: the task region (default: the whole robust workspace)",
    ("[planner]", "metric"): '`"phi_hat_max"`, `"G_norm"`, `"phi_max"` or `"rho_star"`: the cost metric',
    ("[planner]", "weight"): "cost = ∫ (1 + weight·metric) ds, metric in rad or 1",
    ("[planner]", "planner"): "OMPL planner by name (`BITstar`, `RRTstar`, ...)",
    ("[planner]", "iterations"): "the search's budget per query (iterations): it ends there on any machine "
                                 "(default per planner: BIT\\* 7 500 planar, 3 750 spatial)",
    ("[planner]", "time"): "a safety cap per query, s (default: none); a plan it cuts is flagged "
                           "`stopped_by: \"time\"`, not reproducible on another machine",
    ("[planner]", "seed"): "OMPL's seed, 0 to 2³² − 1",
    ("[planner]", "certifiable"): "keep paths where some gain certifies monotonic convergence (ρ\\* ≤ 1 − certify_margin)",
    ("[planner]", "certify_margin"): "the margin of `certifiable` (0.02)",
    ("[[query]]", "name"): "unique query name",
    ("[[query]]", "start"): "start tip, m",
    ("[[query]]", "goal"): "goal tip, m",
    ("[[tolerance]]", "name"): "unique name (`toleranceN`)",
    ("[[tolerance]]", "kind"): "the question asked (required): one of the kinds below",
    ("[[tolerance]] *", "gain"): "controller gain k (`[controller] gain`)",
    ("[[tolerance]] *", "region"): "`{ y = [lo, hi], z = [lo, hi] }` tips, m; `x` too in 3-D (required)",
    ("[[tolerance]] port", "direction"): '`"y"`, `"z"` or `"radial"`; `"x"` too in 3-D, where `"radial"` is a ball',
    ("[[tolerance]] port", "tip_force_over_ei"): "true tip load, 1/m²: a number or `[lo, hi]` (worst over the range)",
    ("[[tolerance]] port", "spacing"): "initial tip-grid spacing, m (extent/8), refined until the answer moves < 1 %",
    ("[[tolerance]] tip_load", "spacing"): "initial tip-grid spacing, m (extent/8), refined until the answer moves < 1 %",
    ("[[tolerance]] tip_load", "port_x"): "true port offset along x, `[lo, hi]` m (3-D only)",
    ("[[tolerance]] tip_load", "port_y"): "true port offset along y, `[lo, hi]` m (none: true port = `port.position`)",
    ("[[tolerance]] tip_load", "port_z"): "true port offset along z, `[lo, hi]` m",
    ("[[tolerance]] *", "tip_force_over_ei"): "the tip load Ft/EI, 1/m², non-zero (required)",
    ("[[tolerance]] *", "sensor_noise"): "`{ position = m, angle = rad }` bounds on each coordinate (required)",
    ("[[tolerance]] *", "length"): "shaft length L, m (`[instrument] length`)",
    ("[[tolerance]] *", "samples"): "insertion depths on the curve (193 in [0.02, 0.98]; 41 across a band)",
    ("[[tolerance]] *", "hold"): '`"tip_force"`, `"port_force"` or `"port_deflection"`: held constant in the flexed Jacobian (planar only)',
    ("[[tolerance]] *", "shaft_angle"): "planar: angle of the port→tip line from the tracker's z axis, rad (0)",
    ("[[tolerance]] *", "shaft_direction"): "3-D: the port→tip direction `[x, y, z]` in the tracker's frame (`[0, 0, 1]`)",
    ("[[tolerance]] *", "noise_sampling"): '`"worst"` (default) or `"random"` (max over uniform draws; planar only)',
    ("[[tolerance]] *", "draws"): 'number of draws for `"random"` (10000)',
    ("[[tolerance]] *", "seed"): 'seed of `"random"` (`[planner] seed`)',
    ("[[tolerance]] tracker_noise", "band"): "required insertion band `[lo, hi]` in r/L, 0 < lo ≤ hi < 1 (required)",
    ("[[tolerance]] tracker_noise", "angle_ratio"): "angle noise = ratio · position noise / L (1.238)",
    ("[[tolerance]] port_placement", "candidates"): '`{ y = [lo, hi], z = [lo, hi] }` (`x` in 3-D): nominal ports to try, m; or `"body_wall"` (required)',
    ("[[tolerance]] port_placement", "spacing"): "candidate spacing, m, > 0 (along the wall for `body_wall`); at most 10,000 candidates (required)",
    ("[[tolerance]] port_placement", "resolution"): "task-region grid spacing, m (`[fields] resolution`)",
    ("[[tolerance]] port_placement", "certify_margin"): "covered means ρ\\* ≤ 1 − margin (`[planner] certify_margin`)",
    ("[[tolerance]] port_placement", "refine"): "refine the best candidate by a compass search (false)",
    ("[[tolerance]] port_placement", "refine_levels"): "step halvings of the refinement (3)",
    ("[anatomy]", "clearance"): "m: instrument radius plus margin, kept from every obstacle (0)",
    ("[anatomy]", "obstacle"): "array of tables `[[anatomy.obstacle]]`",
    ("[anatomy]", "body_wall"): "table `[anatomy.body_wall]` (optional): the inner surface of the insufflated abdomen",
    ("[[anatomy.obstacle]]", "name"): "unique obstacle name",
    ("[[anatomy.obstacle]]", "shape"): '`"sphere"`, `"capsule"`, `"box"` or `"mesh"` (required)',
    ("[[anatomy.obstacle]] *", "center"): "centre `[x, y, z]`, m",
    ("[[anatomy.obstacle]] *", "radius"): "radius, m, > 0",
    ("[[anatomy.obstacle]] capsule", "a"): "one end of the capsule's axis `[x, y, z]`, m",
    ("[[anatomy.obstacle]] capsule", "b"): "the other end, m",
    ("[[anatomy.obstacle]] box", "half_extents"): "three half-lengths > 0, m",
    ("[[anatomy.obstacle]] *", "rpy"): "orientation, rad, roll-pitch-yaw (`[0, 0, 0]`)",
    ("[[anatomy.obstacle]] mesh", "file"): "STL, OBJ or PLY file relative to the scenario: a closed surface",
    ("[[anatomy.obstacle]] mesh", "scale"): "file units → m (1)",
    ("[[anatomy.obstacle]] mesh", "position"): "translation after rotating by `rpy`, m (`[0, 0, 0]`)",
    ("[anatomy.body_wall] ellipsoid", "shape"): '`"ellipsoid"`',
    ("[anatomy.body_wall] ellipsoid", "center"): "centre `[x, y, z]`, m",
    ("[anatomy.body_wall] ellipsoid", "radii"): "three semi-axes > 0, m",
    ("[anatomy.body_wall] mesh", "shape"): '`"mesh"`',
    ("[anatomy.body_wall] mesh", "file"): "STL, OBJ or PLY file relative to the scenario: a closed surface",
    ("[anatomy.body_wall] mesh", "scale"): "file units → m (1)",
    ("[anatomy.body_wall] mesh", "position"): "translation after rotating by `rpy`, m (`[0, 0, 0]`)",
    ("[anatomy.body_wall] mesh", "rpy"): "orientation, rad, roll-pitch-yaw (`[0, 0, 0]`)",
    ("several instruments", "arm"): "array of tables `[[arm]]`, one per instrument arm (replaces the top-level `[robot]`, `[instrument]`, `[port]`, `[controller]`, `[uncertainty]`; a file with both is an error)",
    ("several instruments", "endoscope"): "table `[endoscope]` (optional; required by `triad_placement`): the endoscope's port, view and error box",
    ("several instruments", "setup"): "table `[setup]` (optional): clearances between the instruments",
    ("[[arm]]", "name"): "unique arm name (`armN`): queries, `triad_placement` and `--arm` name it",
    ("[[arm]]", "rest"): "`[x, y, z]`, m: where the arm's tip waits while another instrument moves (required)",
    ("[[arm]]", "robot"): "table `[arm.robot]`: the keys of a URDF `[robot]` (required: several instruments are spatial)",
    ("[[arm]]", "instrument"): "table `[arm.instrument]`: the keys of `[instrument]`",
    ("[[arm]]", "port"): "table `[arm.port]`: the keys of `[port]`",
    ("[[arm]]", "controller"): "table `[arm.controller]`: the keys of `[controller]`",
    ("[[arm]]", "uncertainty"): "table `[arm.uncertainty]`: the keys of `[uncertainty]`, the arm's own error set",
    ("[endoscope]", "port"): "`{ estimate = [x, y, z], position = [x, y, z] }`, m: the endoscope's port (`estimate` defaults to `position`)",
    ("[endoscope]", "look_at"): "`[x, y, z]`, m: the optical axis runs from the port toward this point (required)",
    ("[endoscope]", "insertion"): "m, > 0: the lens's distance from the port along the axis (required)",
    ("[endoscope]", "fov"): "rad, in (0, π): the full angle of the view cone (required)",
    ("[endoscope]", "depth"): "`[near, far]`, m from the lens, 0 ≤ near < far: the depth range seen (required)",
    ("[endoscope]", "uncertainty"): "`{ port_x = [lo, hi], port_y = ..., port_z = ... }`, m: the endoscope port's error box (none: a point)",
    ("[endoscope]", "keep_visible"): "every tip of a planned path inside the view and in line of sight (false)",
    ("[endoscope] port", "estimate"): "the port the endoscope's placement assumes, m",
    ("[endoscope] port", "position"): "the true port, m (required)",
    ("[endoscope] uncertainty", "port_x"): "`[lo, hi]`, m: true port = estimate + offset along x",
    ("[endoscope] uncertainty", "port_y"): "`[lo, hi]`, m: the offset along y",
    ("[endoscope] uncertainty", "port_z"): "`[lo, hi]`, m: the offset along z",
    ("[setup]", "shaft_clearance"): "m, ≥ 0: kept between two instrument shafts and between an instrument and the endoscope, over every port error (0)",
    ("[setup]", "arm_clearance"): "m, > 0: between links of different arms, by the URDFs' collision geometry (omit: no arm checks; the URDF must have collision geometry)",
    ("[[query]] several instruments", "arm"): "the arm that moves, by name (required when there are several arms; the others wait at `rest`)",
    ("[[tolerance]] triad_placement", "instruments"): "the two arms whose ports are chosen, by name (the first two arms)",
    ("[[tolerance]] triad_placement", "candidates"): '`"body_wall"` (candidates spaced along the wall), or `{ ARM = [[x, y, z], ...], ..., endoscope = [...] }` points per role (required)',
    ("[[tolerance]] triad_placement", "spacing"): "m, > 0: candidate spacing along the wall (0.03)",
    ("[[tolerance]] triad_placement", "resolution"): "m: spacing of the task-target grid in `region` (`[fields] resolution`)",
    ("[[tolerance]] triad_placement", "port_spacing"): "m, ≥ 0: smallest distance between any two ports of a triad, a hard constraint (0.06)",
    ("[[tolerance]] triad_placement", "manipulation_angle"): "m\\*, rad, in (0, π): the best angle between the two instrument shafts at a target (60° = 1.0472)",
    ("[[tolerance]] triad_placement", "manipulation_tolerance"): "m_tol, rad, > 0: the score's scale of m − m\\* (15° = 0.2618)",
    ("[[tolerance]] triad_placement", "azimuth_tolerance"): "a_tol, rad, > 0: the score's scale of the azimuth difference a₁ − a₂ (15° = 0.2618)",
    ("[[tolerance]] triad_placement", "coverage_weight"): "W, ≥ 0: the score's weight of an uncovered target (10)",
    ("[[tolerance]] triad_placement", "certify_margin"): "covered means ρ\\* ≤ 1 − margin for each instrument, in [0, 1) (`[planner] certify_margin`)",
    ("[setup]", "patient_clearance"): "m, ≥ 0: every arm link (the URDFs' collision geometry, not the instrument shaft) from the patient's body, the solid inside the body wall, at every covered target and at rest, checked by `setup_placement` (omit: no patient checks)",
    ("[[tolerance]] setup_placement", "instruments"): "the two arms whose bases and ports are chosen, by name (the first two arms)",
    ("[[tolerance]] setup_placement", "bases"): "per instrument arm, `bases.ARM = [{ position = [x, y, z], rpy = [r, p, y] }, ...]` (listed poses; `rpy` defaults to the arm's own) or a grid `{ y, x = [lo, hi], z = [lo, hi], spacing, yaw = [..] }` (bases at height y, axes lo..hi inclusive, rotation R_y(yaw)·R(own `base_rpy`), yaws in [−π, π], default `[0.0]`); its keys are the instrument arms' names (for example `left`, `right`), a grid's `y`, `x`, `z`, `spacing` and `yaw`; an arm without one keeps its own base",
    ("[[tolerance]] setup_placement", "candidates"): "the port candidates, as `triad_placement`'s (required)",
    ("[[tolerance]] setup_placement", "spacing"): "m, > 0: port candidate spacing along the wall (0.03)",
    ("[[tolerance]] setup_placement", "region"): "the task targets' box `{ x = [lo, hi], y = [lo, hi], z = [lo, hi] }` (required)",
    ("[[tolerance]] setup_placement", "resolution"): "m: spacing of the task-target grid in `region` (`[fields] resolution`)",
    ("[[tolerance]] setup_placement", "port_spacing"): "m, ≥ 0: smallest distance between any two ports of a setup, a hard constraint (0.06)",
    ("[[tolerance]] setup_placement", "manipulation_angle"): "m\\*, rad, in (0, π), as `triad_placement` (60° = 1.0472)",
    ("[[tolerance]] setup_placement", "manipulation_tolerance"): "m_tol, rad, > 0, as `triad_placement` (15° = 0.2618)",
    ("[[tolerance]] setup_placement", "azimuth_tolerance"): "a_tol, rad, > 0, as `triad_placement` (15° = 0.2618)",
    ("[[tolerance]] setup_placement", "coverage_weight"): "W, ≥ 0, as `triad_placement` (10)",
    ("[[tolerance]] setup_placement", "certify_margin"): "covered means ρ\\* ≤ 1 − margin for each instrument, in [0, 1) (`[planner] certify_margin`)",
    ("[[tolerance]] setup_placement", "gain"): "the controller gain of the coverage, > 0 (each arm's `[controller] gain`)",
}

EFFECT_DOCS = {
    "port_offset": "the true port is off the declared one, m",
    "joint_offset": "encoder offsets, rad",
    "tracker_offset": "the tracker's frame is shifted, m",
    "gravity_sag": "gravity sag of the links, rad (through the URDF's generalized gravity in 3-D)",
    "shaft_flexion": "the shaft bends under a load, m",
    "port_friction": "port friction opposing the motion, m",
    "link_length": "the links are longer than declared, m (planar)",
    "instrument_length": "the instrument is longer than declared, m",
    "tracker_registration": "the tracker is registered with a rotation (rad) and an offset (m)",
    "backlash": "play between encoder and link, rad (history-dependent)",
    "tracker_latency": "the tracked tip is the true tip at the row's time - tau; s with [sensors] step_time, else "
                       "steps; 0 <= tau <= 5 steps (history-dependent)",
    "joint_geometry": "each actuated joint's origin moved (m) and turned (rad) in its parent frame (URDF arms)",
}

TABLE_TITLES = {
    "": "Top level", "[robot]": "`[robot]`: a planar arm (P1's two links)",
    "[robot] urdf": "`[robot]`: a URDF arm (spatial scenarios)",
    "[robot] coupled_limits": "`[robot] coupled_limits = [ {...}, ... ]`",
    "[uncertainty] 3-D": "`[uncertainty]`: spatial scenarios add",
    "sensor_noise": "`sensor_noise = { ... }` (in `[uncertainty]` and `[[tolerance]]`)",
    "[[tolerance]]": "`[[tolerance]]`: every kind",
    "[[anatomy.obstacle]]": "`[[anatomy.obstacle]]`: every shape",
    "[anatomy.body_wall] ellipsoid": '`[anatomy.body_wall]` with `shape = "ellipsoid"`',
    "[anatomy.body_wall] mesh": '`[anatomy.body_wall]` with `shape = "mesh"`',
    "several instruments": "Top level: a scenario with several instruments adds",
    "[[arm]]": "`[[arm]]`: one instrument arm (several instruments)",
    "[endoscope] port": "`[endoscope] port = { ... }`",
    "[endoscope] uncertainty": "`[endoscope] uncertainty = { ... }`",
    "[[query]] several instruments": "`[[query]]`: several instruments add",
}


def _doc(table: str, key: str, used: set) -> str:
    for t in (table, re.sub(r" \S+$", " *", table)):
        if (t, key) in KEY_DOCS:
            used.add((t, key))
            return KEY_DOCS[(t, key)]
    raise PluginError(f"docs/_hooks/errplan_docs.py: the scenario key {table} {key!r} has no description "
                      "(add it to KEY_DOCS)")


def _table(rows: list[tuple[str, str]]) -> str:
    return "\n".join(["| key | meaning (default) |", "|---|---|", *(f"| `{k}` | {d} |" for k, d in rows)])


def scenario_reference() -> str:
    from errplan import scenario as S

    used: set = set()
    out = ["# Scenario reference", "",
           "Every key a scenario file accepts, table by table. This page is generated by "
           "`python docs/_hooks/errplan_docs.py` from the key tables the parser itself checks files against "
           "(`errplan.scenario.TABLE_KEYS`, "
           "`TOLERANCE_KEYS`, `OBSTACLE_KEYS`, `effect_params`), so it lists exactly what the code accepts. "
           "Units are SI; points are `[y, z]` in a planar scenario and `[x, y, z]` in a spatial one (a `[robot]` "
           "with a `urdf`). A key not listed here is one clear error naming it. Worked examples: "
           "[the file formats](../interfaces.md) and the bundled `scenarios/*.toml`.", ""]
    for table, keys in S.TABLE_KEYS.items():
        title = TABLE_TITLES.get(table, f"`{table}`")
        out += [f"## {title}", "", _table([(k, _doc(table, k, used)) for k in keys]), ""]
        if table == "[[tolerance]]":
            for kind in S.TOLERANCE_KINDS + S.SETUP_TOLERANCE_KINDS:
                keys_k = S.TOLERANCE_KEYS[kind]
                out += [f"### `kind = \"{kind}\"`", "",
                        _table([(k, _doc(f"[[tolerance]] {kind}", k, used)) for k in keys_k]), ""]
                if kind in S.SETUP_TOLERANCE_KINDS:
                    out += [f"`{kind}` belongs to a scenario with several instruments (`[[arm]]`, `[endoscope]`); "
                            "[several instruments](../concepts/several-instruments.md) explains it.", ""]
                if kind in S._TOL_PLANAR:
                    out += [f"In a spatial scenario `{kind}` takes `shaft_direction` and not "
                            + ", ".join(f"`{k}`" for k in S._TOL_PLANAR_ONLY) + ".", ""]
                    _doc(f"[[tolerance]] {kind}", "shaft_direction", used)
        if table == "[[anatomy.obstacle]]":
            for shape, keys_s in S.OBSTACLE_KEYS.items():
                out += [f"### `shape = \"{shape}\"`", "",
                        _table([(k, _doc(f"[[anatomy.obstacle]] {shape}", k, used)) for k in keys_s]), ""]
    out += ["## `[effects.NAME]`", "",
            "Effects present in the truth (what `errplan experiment` simulates and `errplan calibrate` looks for; "
            "[the model](../physics.md)). Every parameter defaults to 0.", "",
            "| effect | parameters (planar) | parameters (spatial, 3 actuated joints) | meaning |", "|---|---|---|---|"]
    for name in S.EFFECT_PARAMS:
        if name not in EFFECT_DOCS:
            raise PluginError(f"docs/_hooks/errplan_docs.py: the effect {name!r} has no description (EFFECT_DOCS)")
        def params_of(*args):
            try:
                return ", ".join(f"`{p}`" for p in S.effect_params(name, *args)) or "—"
            except KeyError:  # an effect of the other dimension only
                return "—"

        p2, p3 = params_of(2), params_of(3, 3)
        out.append(f"| `{name}` | {p2} | {p3} | {EFFECT_DOCS[name]} |")
    stale = set(KEY_DOCS) - used
    if stale:
        raise PluginError(f"docs/_hooks/errplan_docs.py: descriptions of keys the parser does not accept: {sorted(stale)}")
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------ command options
def option_rows(command: str) -> list[tuple[str, str]]:
    """(flags, help) of every option of ``errplan COMMAND`` (or of the program itself for ``errplan``)."""
    from errplan.cli import build_parser

    parser = build_parser()
    if command != "errplan":
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        if command not in sub.choices:
            raise PluginError(f"<!-- errplan-options: {command} -->: no such command ({', '.join(sub.choices)})")
        parser = sub.choices[command]
    rows = []
    for a in parser._actions:
        if isinstance(a, (argparse._SubParsersAction,)):
            continue
        flags = ", ".join(a.option_strings) if a.option_strings else a.dest.upper()
        if a.option_strings and a.nargs != 0 and not isinstance(a, argparse._VersionAction):
            flags += " " + (a.metavar or a.dest.upper())
        text = (a.help or "") % {"default": a.default, "prog": parser.prog} if a.help else ""
        rows.append((flags, text))
    return rows


def options_table(command: str) -> str:
    rows = option_rows(command)
    esc = lambda s: s.replace("|", "\\|")  # noqa: E731
    return "\n".join(["| option | meaning (default) |", "|---|---|",
                      *(f"| `{f}` | {esc(h)} |" for f, h in rows)])


_MARK = re.compile(r"^<!--\s*errplan-options:\s*([\w-]+)\s*-->$", flags=re.M)  # on a line of its own


#: the committed scenario reference, relative to the repository's root
REFERENCE = "docs/reference/scenario.md"


def reference_is_current(root) -> bool:
    """Whether the committed scenario reference under ``root`` is what :func:`scenario_reference` makes."""
    from pathlib import Path

    path = Path(root) / REFERENCE
    return path.is_file() and path.read_text(encoding="utf-8") == scenario_reference()


def on_files(files, config):
    from pathlib import Path

    if not reference_is_current(Path(config["docs_dir"]).parent):
        raise PluginError(f"{REFERENCE} is missing or stale: the parser's key tables changed; regenerate it with "
                          "`python docs/_hooks/errplan_docs.py` and commit it")
    return files


if __name__ == "__main__":  # python docs/_hooks/errplan_docs.py: write the scenario reference
    from pathlib import Path

    out = Path(__file__).resolve().parents[2] / REFERENCE
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(scenario_reference(), encoding="utf-8")
    print(f"wrote {out}")


def on_page_markdown(markdown, page, config, files):
    return _MARK.sub(lambda m: options_table(m.group(1)), markdown)
