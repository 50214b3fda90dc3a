"""errplan's Python API: the entry points the commands use, returning the result objects their tables
and JSON are made from. ``import errplan`` exposes them (loaded on first use, so the import stays light).

====================  ==========================  ==========================================================
function              command                     returns
====================  ==========================  ==========================================================
:func:`load_scenario` every command               :class:`~errplan.scenario.Scenario` (validated, checked
                                                  against its robot)
:func:`load_models`   (the steps below)           one :class:`~errplan.models.ArmModel` per arm, built once
:func:`compute_fields` ``errplan fields``         :class:`~errplan.fields.MetricField` (``.save(npz)``,
                                                  ``.summary()``, the arrays by name)
:func:`plan`          ``errplan plan``            :class:`~errplan.planning.ScenarioPlan` with gains and
                                                  simulations (``.to_json()`` is the plan JSON)
:func:`tolerances`    ``errplan tolerance``       a list of :class:`~errplan.tolerance.ToleranceResult`
                                                  (``.to_dict()`` each)
:func:`run_experiment` ``errplan experiment``     :class:`~errplan.experiment.ExperimentResult` (``.data``
                                                  is the measured data, ``.data.write_csv(path)``)
:func:`calibrate`     ``errplan calibrate``       :class:`~errplan.calibration.CalibrationReport`
                                                  (``.to_json()``, ``.text()``)
====================  ==========================  ==========================================================

Every function takes a scenario object or the path of a scenario file. Bad input raises one
:class:`errplan.ErrplanError` (a :class:`~errplan.ScenarioError`, :class:`~errplan.DataError` or
:class:`~errplan.InfeasibleError`) whose message is the line the command prints. Units are SI
(docs/physics.md). The top layer beside :mod:`errplan.cli`: it may import anything below it; nothing in
errplan imports it except the CLI.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from .kinematics import check_scenario
from .scenario import Scenario, Setup, read_scenario, read_setup, scenario_from_dict

__all__ = ["Scenario", "Setup", "load_scenario", "load_setup", "load_arm", "load_models", "parse_scenario", "compute_fields", "plan", "tolerances", "run_experiment",
           "calibrate"]

Progress = Callable[[float, str], None]


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario TOML file, validate every key and check it against its robot.

    Every key is checked (the scenario reference lists them), then the scenario against its robot: the
    URDF loads, the shaft reaches through the port, the anatomy's meshes are closed and clear of the port.

    Parameters
    ----------
    path : str or pathlib.Path
        The scenario file (UTF-8 TOML). Relative paths inside it (a URDF, meshes) resolve against its folder.

    Returns
    -------
    Scenario
        The validated scenario: frozen dataclasses, one per table; ``.dim`` is 2 (planar) or 3 (a URDF arm).

    Raises
    ------
    errplan.ScenarioError
        One error naming the file, the key, the value and what was expected.

    Examples
    --------
    Run from the repository's root:

    >>> import errplan
    >>> sc = errplan.load_scenario("scenarios/beasley2004_port.toml")
    >>> sc.name, sc.dim, [q.name for q in sc.queries]
    ('beasley2004-port', 2, ['N-to-L', 'across-deep', 'past-the-port'])
    >>> sc.port.estimate
    (0.02, 0.17)
    """
    sc = read_scenario(path)
    check_scenario(sc)
    check_anatomy(sc)
    return sc


def load_setup(path: str | Path) -> Setup:
    """Read a scenario file with one or several arms (``[[arm]]``) once into per-arm scenarios, and check
    every arm as :func:`load_scenario` checks a scenario, then the setup (:func:`check_setup`)."""
    st = read_setup(path)
    for sc in st.arms:
        check_scenario(sc)
        check_anatomy(sc)
    check_setup(st)
    return st


def load_arm(path: str | Path, arm: str | None) -> Scenario:
    """The scenario of one arm of a file (``arm`` None: a one-instrument file, or its only arm); the
    whole file is read and checked (:func:`load_setup`)."""
    return load_setup(path).arm(arm)


def check_setup(st: Setup) -> None:
    """The checks of a several-arm setup that need geometry: each rest point robustly reachable and
    clear of the anatomy, with the arm checks on every arm's collision geometry readable and the arms
    at rest (each at the IK putting its wrist on the rigid shaft from its rest point through its
    estimated port) at least ``arm_clearance`` apart, the endoscope's port on the body wall, and the
    scenario's ports at least each ``triad_placement`` query's ``port_spacing`` apart. One
    :class:`errplan.ScenarioError`."""
    if not st.several:
        return
    import numpy as np

    from .errors import ScenarioError
    from .fields.compute import anatomy_model
    from .errorset import error_set
    from .kinematics import arm_for
    from .kinematics.shaft import lever_wrist

    for name, sc, rest in zip(st.arm_names, st.arms, st.rests):
        es = error_set(sc)[0]
        corners = es.port_corners()
        x = np.asarray(rest, float)
        wr = lever_wrist(x[None, :], corners, sc.instrument.length)
        if not bool(np.all(arm_for(sc.robot).reachable(wr))):
            raise ScenarioError(f"{st.source}: [[arm]] {name!r} rest = {list(rest)}: expected a tip the arm reaches "
                                "through every true port of its box (rest point unreachable)")
        m = anatomy_model(sc, es)
        if m is not None and not bool(m.tip_clear(x)):
            raise ScenarioError(f"{st.source}: [[arm]] {name!r} rest = {list(rest)}: expected a tip robustly clear "
                                f"of the anatomy by [anatomy] clearance {m.required:g} m (rest point not clear)")
    if st.arm_clearance is not None:  # arm checks need every arm's collision geometry
        from .errors import ErrplanError
        from .kinematics.urdf.collision import ArmCollision

        from .kinematics.urdf.collision import arm_at_tip, closest_pair

        held = []  # the arms at rest: each at the IK putting its wrist on the rigid shaft through its port
        for name, sc, rest in zip(st.arm_names, st.arms, st.rests):
            try:
                geo = ArmCollision.from_arm(arm_for(sc.robot))
            except ErrplanError as err:
                raise ScenarioError(f"{st.source}: [setup] arm_clearance = {st.arm_clearance:g}: arm {name!r}: "
                                    f"{err}") from None
            try:
                q = arm_at_tip(geo.arm, rest, sc.port.estimate, sc.instrument.length)
            except ErrplanError as err:
                raise ScenarioError(f"{st.source}: [[arm]] {name!r} rest = {list(rest)}: {err} (rest point "
                                    "unreachable)") from None
            held.append((name, rest, geo, q))
        for i in range(len(held)):
            for j in range(i + 1, len(held)):
                (na, ra, ga, qa), (nb, rb, gb, qb) = held[i], held[j]
                c = closest_pair(ga, qa, gb, qb)
                if c.distance < st.arm_clearance:
                    raise ScenarioError(f"{st.source}: [[arm]] {na!r} rest = {list(ra)} and {nb!r} rest = {list(rb)}: "
                                        f"their arms are {c.distance * 1000:.1f} mm apart ({c.name_a!r} and "
                                        f"{c.name_b!r}), expected at least [setup] arm_clearance = "
                                        f"{st.arm_clearance:g} m (rest point not clear)")
    e = st.endoscope
    if e is not None:
        sc0 = st.arms[0]
        m = anatomy_model(sc0)
        if m is not None and m.wall[6] > 0:
            from .anatomy.setup import endoscope_box

            box = endoscope_box(e)
            tol = max(0.001, float(np.max(np.linalg.norm(box - box.mean(axis=0), axis=1))))
            gap = m.wall_gap(np.asarray(e.port.estimate, float))
            if gap > tol:
                raise ScenarioError(f"{st.source}: [endoscope] port.estimate = {list(e.port.estimate)}: "
                                    f"{gap * 1000:.1f} mm from the body wall (more than {tol * 1000:.1f} mm): expected "
                                    "a port on [anatomy.body_wall] (endoscope port off the wall)")
    ports = [(f"[[arm]] {n!r} port.estimate", sc.port.estimate) for n, sc in zip(st.arm_names, st.arms)]
    if e is not None:
        ports.append(("[endoscope] port.estimate", e.port.estimate))
    for t in st.triads:
        ps = t.get("port_spacing", 0.0)
        for i in range(len(ports)):
            for j in range(i + 1, len(ports)):
                d = float(np.linalg.norm(np.subtract(ports[i][1], ports[j][1])))
                if d < ps:
                    raise ScenarioError(f"{st.source}: {ports[i][0]} and {ports[j][0]} are {d * 1000:.1f} mm apart: "
                                        f"expected ports at least [[tolerance]] {t.name!r} port_spacing = {ps:g} m apart")


def parse_scenario(doc: Mapping[str, Any], source: str = "<memory>") -> Scenario:
    """:func:`load_scenario` for an already parsed TOML document.

    Parameters
    ----------
    doc : Mapping
        The document as :mod:`tomllib` returns it: tables as dicts. Missing tables take their defaults
        (P1's planar arm, gain 1, the rigid controller).
    source : str, optional
        The file the document came from: named in error messages; relative paths resolve against its
        folder.

    Returns
    -------
    Scenario
        The validated scenario.

    Raises
    ------
    errplan.ScenarioError
        One error naming the key, the value and what was expected.

    Examples
    --------
    >>> import errplan
    >>> sc = errplan.parse_scenario({"instrument": {"length": 0.32},
    ...                              "port": {"position": [0.0, 0.16], "estimate": [0.02, 0.17]}})
    >>> sc.dim, sc.controller.gain, sc.controller.jacobian
    (2, 1.0, 'rigid')
    >>> errplan.parse_scenario({"controller": {"gain": -1.0}})
    Traceback (most recent call last):
    ...
    errplan.errors.ScenarioError: <memory>: [controller] gain = -1.0: expected a number > 0
    """
    sc = scenario_from_dict(doc, source)
    check_scenario(sc)
    check_anatomy(sc)
    return sc


def check_anatomy(sc: Scenario) -> None:
    """The checks of ``[anatomy]`` that need its geometry (meshes load and are closed, the port box is
    clear of every obstacle, no query endpoint inside one): one :class:`errplan.ScenarioError`."""
    an = sc.anatomy
    if an is None:
        return
    from .anatomy import check
    from .errorset import error_set

    check(sc, error_set(sc)[0].port_corners())


def _part(progress: Progress | None, lo: float, hi: float) -> Progress | None:
    """``progress`` for one part of a job: its fractions 0..1 mapped to ``lo..hi``
    (:func:`errplan.pipeline.part_progress`)."""
    from .pipeline import part_progress

    return part_progress(progress, lo, hi)


def _scenario(scenario):
    """The arm's model (:class:`errplan.models.ArmModel`), built here once for every step below: a model
    passes through, a scenario is built, a path is loaded and built."""
    from .models import ArmModel, arm_model

    if isinstance(scenario, ArmModel):
        return scenario
    return arm_model(scenario if isinstance(scenario, Scenario) else load_scenario(scenario))


def load_models(path: str | Path) -> tuple:
    """Every instrument arm of a scenario file built once (:func:`errplan.models.build`).

    One :class:`~errplan.models.ArmModel` per ``[[arm]]`` (in file order; a one-instrument file gives one,
    named ``"arm"``), each as it moves among the others (their held shafts and the endoscope's among its
    obstacles). Every function here takes a model where it takes a scenario, and uses its built parts
    (arm, error set, truth, anatomy) instead of building them again; a model also answers every table of
    its scenario (``m.queries``, ``m.planner``, ...).

    Parameters
    ----------
    path : str or pathlib.Path
        A scenario file (one instrument, or several ``[[arm]]`` tables); read and checked as
        :func:`load_setup` does.

    Returns
    -------
    tuple of ArmModel
        ``.arm_name``, ``.dim``, ``.scenario`` (the plain data), ``.arm`` (kinematics), ``.errors`` /
        ``.true_errors`` (error sets), ``.truth`` (the true robot), ``.anatomy_model`` (obstacles as this arm
        sees them, or None), the controller's ``.jacobian``, ``.gain``, ``.noise``, ``.estimate``.

    Examples
    --------
    >>> import errplan
    >>> (m,) = errplan.api.load_models("scenarios/beasley2004_port.toml")
    >>> m.arm_name, m.dim, m.errors.dim, m.truth.dim
    ('arm', 2, 2, 2)
    """
    from .models import build

    return build(load_setup(path))


def compute_fields(scenario: Scenario | str | Path, resolution: float | None = None, *,
                   metrics: Sequence[str] | None = None, rho_star: bool = False, samples: int | None = None,
                   workers: int | None = None, scheduler: str | None = None, progress: Progress | None = None):
    """Worst-case metric fields over the tip grid (``errplan fields``).

    At every tip of the grid, the worst case over the scenario's error set of ‖G‖, φ̂max and the exact
    |φmax| at the scenario's gain, and on request the best achievable contraction ρ* with its gain k*
    (docs/physics.md, "Metrics").

    Parameters
    ----------
    scenario : Scenario or str or pathlib.Path
        A scenario, or the path of a scenario file.
    resolution : float, optional
        Grid spacing, m (default: the scenario's ``[fields] resolution``).
    metrics : sequence of str, optional
        Names among ``G_norm``, ``phi_hat_max``, ``phi_max``, ``rho_star`` (default: the first three,
        plus ``rho_star`` and ``k_star`` with ``rho_star=True``).
    rho_star : bool, optional
        Also compute ``rho_star`` and ``k_star`` (default False).
    samples : int, optional
        Error-set samples per uncertain axis before refinement (default: ``[uncertainty] samples``).
    workers : int, optional
        Local worker processes for the grid's tiles (default: all cores).
    scheduler : str, optional
        Address of a dask.distributed scheduler to run the tiles on instead (same arrays).
    progress : callable, optional
        Called as ``progress(fraction, message)``.

    Returns
    -------
    MetricField
        ``.valid`` and the metric arrays on the grid ``.axes`` (NaN outside the workspace);
        ``.save(path)`` writes the npz of docs/interfaces.md, ``.summary()`` the command's table.

    Examples
    --------
    P1's Fig. 5 setup at 10 mm on one worker:

    >>> import errplan
    >>> mf = errplan.compute_fields("scenarios/beasley2004_port.toml", 0.01, workers=1)
    >>> s = mf.summary()
    >>> s["valid_points"], s["grid"], round(s["share_G_below_1"], 2)
    (961, [49, 39], 0.72)
    """
    from .fields import compute_fields as _fields
    from .fields import parse_metrics

    sc = _scenario(scenario)
    chosen = parse_metrics(",".join(metrics) if metrics is not None else None, rho_star)
    return _fields(sc, resolution, samples=samples, progress=progress, metrics=chosen, workers=workers,
                   scheduler=scheduler)


def plan(scenario: Scenario | str | Path, *, query: str | None = None, planner: str | None = None,
         time: float | None = None, seed: int | None = None, record: str | Path | None = None,
         progress: Progress | None = None, workers: int = 1, iterations: int | None = None):
    """Plan every query, certify per-segment gains and simulate planned versus direct paths (``errplan plan``).

    Parameters
    ----------
    scenario : Scenario or str or pathlib.Path
        A scenario, or the path of a scenario file.
    query : str, optional
        Plan only the query of this name (default: every query).
    planner : str, optional
        OMPL planner by name (default: ``[planner] planner``).
    time : float, optional
        A time cap per query, s (default: ``[planner] time``, none). A search it cuts depends on the
        machine: its ``stopped_by`` says "time".
    seed : int, optional
        OMPL's seed (default: ``[planner] seed``).
    record : str or pathlib.Path, optional
        Write the rerun recording (``.rrd``) there.
    progress : callable, optional
        Called as ``progress(fraction, message)``.
    workers : int, optional
        Local processes for the fields' tiles and for the queries' gains and simulations (default 1);
        the result does not depend on it.
    iterations : int, optional
        The search's budget per query (default: ``[planner] iterations``, else the planner's default):
        the search ends there on any machine.

    Returns
    -------
    ScenarioPlan
        ``.queries`` (one :class:`~errplan.planning.QueryPlan` each, with ``planned``, ``direct``, gains
        and simulations), ``.costmap`` (the fields it planned on), ``.runs`` (the simulated runs of the
        summary table) and ``.to_json()``, the plan JSON of docs/interfaces.md.

    Examples
    --------
    >>> import errplan
    >>> result = errplan.plan("scenarios/beasley2004_port.toml", query="N-to-L")
    >>> q = result.to_json()["queries"][0]
    >>> q["name"], all(g["certified_G_norm"] < 1 for g in q["gains"]), q["simulation"]["planned"]["monotonic"]
    ('N-to-L', True, True)
    """
    from .pipeline import run_pipeline
    from .planning import plan_scenario

    sc = _scenario(scenario)
    result = plan_scenario(sc, query=query, planner=planner, time=time, seed=seed, iterations=iterations,
                           progress=_part(progress, 0.0, 0.5), workers=workers)
    res = run_pipeline(sc, result.queries, result.costmap.mf, record=None if record is None else str(record),
                       progress=_part(progress, 0.5, 1.0), workers=workers)
    result.runs = res["runs"]
    return result


def tolerances(scenario: Scenario | str | Path, *, workers: int | None = None, scheduler: str | None = None,
               progress: Progress | None = None) -> list:
    """Answer every ``[[tolerance]]`` query of a scenario (``errplan tolerance``).

    Parameters
    ----------
    scenario : Scenario or str or pathlib.Path
        A scenario, or the path of a scenario file.
    workers : int, optional
        Local worker processes for port-placement candidates (default: all cores).
    scheduler : str, optional
        Address of a dask.distributed scheduler to run the candidates on instead.
    progress : callable, optional
        Called as ``progress(fraction, message)``.

    Returns
    -------
    list of ToleranceResult
        One per query, in file order; ``.to_dict()`` of each is an entry of the tolerance JSON.

    Examples
    --------
    How far may the true port be from its estimate along y before the worst-case ‖G‖ reaches 1
    somewhere on P1's axis (the first query of ``beasley2004_port.toml``)?

    >>> import errplan
    >>> sc = errplan.load_scenario("scenarios/beasley2004_port.toml")
    >>> [r] = errplan.tolerances(sc.with_(tolerances=sc.tolerances[:1]), workers=1)
    >>> d = r.to_dict()
    >>> d["name"], d["kind"], f"{1000 * d['value']:.1f} mm", d["binding_point"]
    ('port-y along y = 0', 'port', '15.1 mm', [-0.002, 0.42])
    """
    from .tolerance import run_all

    return run_all(_scenario(scenario), progress=progress, workers=workers, scheduler=scheduler)


def run_experiment(scenario: Scenario | str | Path, seed: int = 0, *, starts: int = 8, max_steps: int = 60,
                   dwell: int = 10, runs=None):
    """A P1-style bench run on the scenario's truth (``errplan experiment``), deterministic from ``seed``.

    The truth is the declared model plus the scenario's ``[effects]`` and the sensor noise of ``[sensors]``.

    Parameters
    ----------
    scenario : Scenario or str or pathlib.Path
        A scenario, or the path of a scenario file.
    seed : int, optional
        Seed of the sensor noise (default 0).
    starts : int, optional
        Start tips: P1's L, M, N where reachable, then spread over the workspace (default 8).
    max_steps : int, optional
        Controller commands per run at most (default 60).
    dwell : int, optional
        Steps recorded after a run first arrives within tolerance (default 10).
    runs : optional
        Explicit ``(start, target)`` runs instead of the starts times P1's targets (experiment design).

    Returns
    -------
    ExperimentResult
        ``.data`` the measured data (``.data.write_csv(path)`` writes the CSV of docs/interfaces.md),
        ``.starts``, ``.targets``, ``.status`` per run.

    Examples
    --------
    One start, P1's eight targets 20 mm away:

    >>> import errplan
    >>> bench = errplan.run_experiment("scenarios/beasley2004_port.toml", seed=0, starts=1)
    >>> len(bench.status), set(bench.status)
    (8, {'converged'})
    """
    from .experiment import run_experiment as _run

    return _run(_scenario(scenario), seed, n_starts=starts, max_steps=max_steps, dwell=dwell, runs=runs)


def calibrate(scenario: Scenario | str | Path, data, *, validate=None, seed: int = 0, folds: int = 5,
              effects: Sequence[str] | None = None, progress: Progress | None = None):
    """Close the loop with measured data (``errplan calibrate``): residual, effect found, error before and after.

    Parameters
    ----------
    scenario : Scenario or str or pathlib.Path
        The declared model.
    data : str or pathlib.Path or MeasuredData
        A measured-data CSV path or :class:`~errplan.experiment.MeasuredData` (for example
        ``run_experiment(...).data``).
    validate : str or pathlib.Path or MeasuredData, optional
        Held-out data for the errors before and after (default: the errors on ``data``).
    seed : int, optional
        Seed of the held-out split (default 0).
    folds : int, optional
        Held-out folds of runs (default 5).
    effects : sequence of str, optional
        Candidate effects (default: the whole catalogue of docs/physics.md).
    progress : callable, optional
        Called as ``progress(fraction, message)``.

    Returns
    -------
    CalibrationReport
        ``.selected``, ``.explained``, ``.text()`` and ``.to_json()`` (the calibrate JSON).

    Examples
    --------
    A bench whose true port is 2 mm / −1 mm off the declared one:

    >>> import errplan
    >>> sc = errplan.load_scenario("scenarios/beasley2004_port.toml")
    >>> truth = sc.with_(effects={"port_offset": {"dy": 0.002, "dz": -0.001}})
    >>> report = errplan.calibrate(sc, errplan.run_experiment(truth, seed=0, starts=2).data)
    >>> found = report.to_json()["parameters"]["port_offset"]
    >>> report.selected, report.explained, round(1000 * found["dy"], 1), round(1000 * found["dz"], 1)
    (['port_offset'], True, 2.0, -1.0)
    """
    from .calibration import calibrate as _calibrate
    from .experiment import read_measured_csv

    sc = _scenario(scenario)

    def measured(d):
        return read_measured_csv(d, sc) if isinstance(d, (str, Path)) else d

    return _calibrate(sc, measured(data), validate=None if validate is None else measured(validate), seed=seed,
                      folds=folds, progress=progress, effects=effects)
