"""errplan's Python API: the entry points the commands use, returning the result objects their tables
and JSON are made from. ``import errplan`` exposes them (loaded on first use, so the import stays light).

====================  ==========================  ==========================================================
function              command                     returns
====================  ==========================  ==========================================================
:func:`load_scenario` every command               :class:`~errplan.scenario.Scenario` (validated, checked
                                                  against its robot)
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

__all__ = ["Scenario", "Setup", "load_scenario", "load_setup", "load_arm", "parse_scenario", "compute_fields", "plan", "tolerances", "run_experiment",
           "calibrate"]

Progress = Callable[[float, str], None]


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario TOML file, validate every key and check it against its robot (the URDF loads, the
    shaft reaches the port). Raises one :class:`errplan.ScenarioError` naming the key and value."""
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
    clear of the anatomy, the endoscope's port on the body wall, and the scenario's ports at least each
    ``triad_placement`` query's ``port_spacing`` apart. One :class:`errplan.ScenarioError`."""
    if not st.several:
        return
    import numpy as np

    from .errors import ScenarioError
    from .fields.compute import anatomy_model
    from .fields.errorset import error_set
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

        for name, sc in zip(st.arm_names, st.arms):
            try:
                ArmCollision.from_arm(arm_for(sc.robot))
            except ErrplanError as err:
                raise ScenarioError(f"{st.source}: [setup] arm_clearance = {st.arm_clearance:g}: arm {name!r}: "
                                    f"{err}") from None
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
    """:func:`load_scenario` for an already parsed TOML document (relative paths resolve against
    ``source``'s folder)."""
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
    from .fields.errorset import error_set

    check(sc, error_set(sc)[0].port_corners())


def _part(progress: Progress | None, lo: float, hi: float) -> Progress | None:
    """``progress`` for one part of a job: its fractions 0..1 mapped to ``lo..hi``."""
    if progress is None:
        return None
    return lambda f, msg="": progress(lo + (hi - lo) * f, msg)


def _scenario(scenario: Scenario | str | Path) -> Scenario:
    return scenario if isinstance(scenario, Scenario) else load_scenario(scenario)


def compute_fields(scenario: Scenario | str | Path, resolution: float | None = None, *,
                   metrics: Sequence[str] | None = None, rho_star: bool = False, samples: int | None = None,
                   workers: int | None = None, scheduler: str | None = None, progress: Progress | None = None):
    """Worst-case metric fields over the tip grid (``errplan fields``).

    Parameters
    ----------
    resolution : grid spacing in m (default: the scenario's ``[fields] resolution``).
    metrics : names among ``G_norm, phi_hat_max, phi_max, rho_star`` (default: the first three, plus
        ``rho_star`` and ``k_star`` with ``rho_star=True``).
    samples : error-set samples per uncertain axis before refinement (default: the scenario's).
    workers, scheduler : local worker processes (default: all cores) or a dask.distributed address.

    Returns
    -------
    MetricField : ``.valid`` and the metric arrays on the grid ``.axes`` (NaN outside the workspace),
        ``.save(path)`` writes the npz of docs/interfaces.md, ``.summary()`` the command's table.
    """
    from .fields import compute_fields as _fields
    from .fields import parse_metrics

    sc = _scenario(scenario)
    chosen = parse_metrics(",".join(metrics) if metrics is not None else None, rho_star)
    return _fields(sc, resolution, samples=samples, progress=progress, metrics=chosen, workers=workers,
                   scheduler=scheduler)


def plan(scenario: Scenario | str | Path, *, query: str | None = None, planner: str | None = None,
         time: float | None = None, seed: int | None = None, record: str | Path | None = None,
         progress: Progress | None = None):
    """Plan every query (or the one named ``query``), certify per-segment gains and simulate planned versus
    direct paths (``errplan plan``); ``record`` writes the rerun recording there.

    Returns
    -------
    ScenarioPlan : ``.queries`` (one :class:`~errplan.planning.QueryPlan` each, with ``planned``,
        ``direct``, gains and simulations), ``.costmap`` (the fields it planned on), ``.runs`` (the
        simulated runs of the summary table) and ``.to_json()``, the plan JSON of docs/interfaces.md.
    """
    from .pipeline import run_pipeline
    from .planning import plan_scenario

    sc = _scenario(scenario)
    result = plan_scenario(sc, query=query, planner=planner, time=time, seed=seed, progress=_part(progress, 0.0, 0.5))
    res = run_pipeline(sc, result.queries, result.costmap.mf, record=None if record is None else str(record),
                       progress=_part(progress, 0.5, 1.0))
    result.runs = res["runs"]
    return result


def tolerances(scenario: Scenario | str | Path, *, workers: int | None = None, scheduler: str | None = None,
               progress: Progress | None = None) -> list:
    """Answer every ``[[tolerance]]`` query (``errplan tolerance``): a list of
    :class:`~errplan.tolerance.ToleranceResult`, ``.to_dict()`` each being an entry of the tolerance JSON."""
    from .tolerance import run_all

    return run_all(_scenario(scenario), progress=progress, workers=workers, scheduler=scheduler)


def run_experiment(scenario: Scenario | str | Path, seed: int = 0, *, starts: int = 8, max_steps: int = 60,
                   dwell: int = 10, runs=None):
    """A P1-style bench run on the scenario's truth (``errplan experiment``), deterministic from ``seed``.

    Returns
    -------
    ExperimentResult : ``.data`` the measured data (``.data.write_csv(path)`` writes the CSV of
        docs/interfaces.md), ``.starts``, ``.targets``, ``.status`` per run.
    """
    from .experiment import run_experiment as _run

    return _run(_scenario(scenario), seed, n_starts=starts, max_steps=max_steps, dwell=dwell, runs=runs)


def calibrate(scenario: Scenario | str | Path, data, *, validate=None, seed: int = 0, folds: int = 5,
              effects: Sequence[str] | None = None, progress: Progress | None = None):
    """Close the loop with measured data (``errplan calibrate``): residual, effect found, error before and after.

    ``data`` and ``validate``: a measured-data CSV path or :class:`~errplan.experiment.MeasuredData` (for
    example ``run_experiment(...).data``). Returns a :class:`~errplan.calibration.CalibrationReport`:
    ``.selected``, ``.explained``, ``.text()`` and ``.to_json()`` (the calibrate JSON).
    """
    from .calibration import calibrate as _calibrate
    from .experiment import read_measured_csv

    sc = _scenario(scenario)

    def measured(d):
        return read_measured_csv(d, sc) if isinstance(d, (str, Path)) else d

    return _calibrate(sc, measured(data), validate=None if validate is None else measured(validate), seed=seed,
                      folds=folds, progress=progress, effects=effects)
