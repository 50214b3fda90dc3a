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
from .scenario import Scenario, read_scenario, scenario_from_dict

__all__ = ["Scenario", "load_scenario", "parse_scenario", "compute_fields", "plan", "tolerances", "run_experiment",
           "calibrate"]

Progress = Callable[[float, str], None]


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario TOML file, validate every key and check it against its robot (the URDF loads, the
    shaft reaches the port). Raises one :class:`errplan.ScenarioError` naming the key and value."""
    sc = read_scenario(path)
    check_scenario(sc)
    check_anatomy(sc)
    return sc


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
