"""errplan: plan instrument-tip paths for minimally invasive surgical robots with
kinematic-error metrics (Beasley, Howe & Dupont, ICRA 2004; Beasley & Howe) as costs.

Conventions (docs/physics.md): SI units, points are ``[y, z]`` (planar) or ``[x, y, z]`` (a URDF arm)
with the coordinate axis last.

The Python API (:mod:`errplan.api`, loaded on first use so that ``import errplan`` stays light):
:func:`load_scenario`, :func:`compute_fields`, :func:`plan`, :func:`tolerances`, :func:`run_experiment`,
:func:`calibrate`; see docs/api.md.
"""
from .errors import DataError, ErrplanError, InfeasibleError, ScenarioError

__version__ = "0.1.0"
_API = ("load_scenario", "load_models", "parse_scenario", "compute_fields", "plan", "tolerances", "run_experiment", "calibrate", "Scenario")
__all__ = [*_API, "ErrplanError", "ScenarioError", "DataError", "InfeasibleError", "__version__"]


def __getattr__(name: str):
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'errplan' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
