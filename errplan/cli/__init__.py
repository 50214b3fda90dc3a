"""The ``errplan`` command line. Each command lives in its own module of this package
(``errplan.cli.<command>``) and is imported only when run, so ``errplan fields`` never pays for
ompl, casadi or rerun at start-up. Any :class:`errplan.ErrplanError` becomes one line on stderr
and exit code 2; nothing is written in that case (outputs are written atomically at the end).
"""
from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import ErrplanError

COMMANDS = ("demo", "fields", "plan", "tolerance", "experiment", "calibrate", "view")


def _positive_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a number") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"{s!r}: expected a number > 0")
    return v


class _OneLineParser(argparse.ArgumentParser):
    """Usage errors are one line on stderr and exit code 2, like every other errplan error."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _OneLineParser(
        prog="errplan",
        description="Plan instrument-tip paths with kinematic-error metrics as costs (Beasley et al.).",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_OneLineParser)

    s = sub.add_parser("demo", help="the bundled default scenario end to end: fields, plan, gains, simulation")
    s.add_argument("--scenario", default=None, help="scenario file (default: the bundled beasley2004_bounded.toml)")
    s.add_argument("--record", default="errplan-demo.rrd", help="rerun recording to write (default: %(default)s)")
    s.add_argument("--json", default=None, help="also write the plan JSON here")

    s = sub.add_parser("fields", help="worst-case metric fields of a scenario -> npz")
    s.add_argument("scenario")
    s.add_argument("--out", required=True, help="npz file to write")
    s.add_argument("--resolution", type=_positive_float, default=None, help="grid spacing, m (default: [fields] resolution)")
    s.add_argument("--rho-star", action="store_true", help="also compute rho_star and k_star (best achievable contraction)")
    s.add_argument("--samples", type=int, default=None, help="samples per uncertain axis (default: [uncertainty] samples)")
    s.add_argument("--json", default=None, help="also write the summary as JSON")

    s = sub.add_parser("plan", help="plan every query, pick gains, simulate planned vs direct")
    s.add_argument("scenario")
    s.add_argument("--json", default=None, help="plan JSON to write")
    s.add_argument("--record", default=None, help="rerun recording (.rrd) to write")
    s.add_argument("--query", default=None, help="plan only this query (by name)")
    s.add_argument("--time", type=_positive_float, default=None, help="planner time per query, s (default: [planner] time)")
    s.add_argument("--planner", default=None, help="OMPL planner name (default: [planner] planner)")
    s.add_argument("--seed", type=int, default=None, help="OMPL seed (default: [planner] seed)")

    s = sub.add_parser("tolerance", help="tolerance-design queries of a scenario")
    s.add_argument("scenario")
    s.add_argument("--json", default=None, help="tolerance JSON to write (answers and plot-ready curves)")

    s = sub.add_parser("experiment", help="a P1-style bench run on the scenario's truth -> measured-data CSV")
    s.add_argument("scenario")
    s.add_argument("--out", required=True, help="measured-data CSV to write")
    s.add_argument("--seed", type=int, default=0, help="seed of the sensor noise (default: %(default)s)")
    s.add_argument("--starts", type=int, default=8,
                   help="start tips: P1's L, M, N where reachable, then spread over the workspace (default: %(default)s)")
    s.add_argument("--max-steps", type=int, default=60, help="commands per run at most (default: %(default)s)")
    s.add_argument("--dwell", type=int, default=10,
                   help="steps recorded after a run first arrives within tolerance (default: %(default)s)")

    s = sub.add_parser("calibrate", help="close the loop: residual, effect found, error before/after")
    s.add_argument("scenario")
    s.add_argument("data")
    s.add_argument("--validate", default=None, help="held-out CSV for the before/after errors")
    s.add_argument("--json", default=None)
    s.add_argument("--record", default=None)
    s.add_argument("--export-scenario", default=None, help="write the scenario with the found effects under [effects]")
    s.add_argument("--seed", type=int, default=0, help="seed for the held-out split")
    s.add_argument("--folds", type=int, default=5, help="held-out folds of runs (default: %(default)s)")

    s = sub.add_parser("view", help="open a recording in the rerun viewer")
    s.add_argument("recording")
    s.add_argument("--web", action="store_true",
                   help="serve the rerun web viewer (http://localhost:9090) instead of opening the native viewer")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        mod = importlib.import_module(f"errplan.cli.{args.command}")
        return int(mod.run(args) or 0)
    except ErrplanError as e:
        if sys.stderr.isatty():  # clear an updating progress line first
            sys.stderr.write("\r" + " " * 60 + "\r")
        print(f"errplan {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # pragma: no cover
        print("errplan: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
