"""errplan's exceptions. The CLI turns any :class:`ErrplanError` into one line on stderr and exit 2."""


class ErrplanError(ValueError):
    """Base class of every error errplan reports to a user (bad input, infeasible request)."""


class ScenarioError(ErrplanError):
    """A scenario file is malformed: the message names the key, the value and what was expected."""


class DataError(ErrplanError):
    """A measured-data CSV is malformed (missing columns, NaN, wrong types)."""


class InfeasibleError(ErrplanError):
    """A request cannot be met: a start outside the workspace, no path found, no certifiable gain."""
