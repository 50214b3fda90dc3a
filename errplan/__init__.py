"""errplan: plan instrument-tip paths for minimally invasive surgical robots with
kinematic-error metrics (Beasley, Howe & Dupont, ICRA 2004; Beasley & Howe) as costs.

Conventions (docs/physics.md): SI units, points are ``[y, z]`` with the coordinate axis last,
an angle ``a`` is the direction ``(sin a, cos a)``.
"""
from .errors import DataError, ErrplanError, InfeasibleError, ScenarioError
from .scenario import Scenario, load_scenario, parse_scenario

__version__ = "0.1.0"
__all__ = ["Scenario", "load_scenario", "parse_scenario", "ErrplanError", "ScenarioError",
           "DataError", "InfeasibleError", "__version__"]
