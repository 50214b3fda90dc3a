"""The ``errplan`` command line. Each command lives in its own module of this package
(``errplan.cli.<command>``) and is imported only when run, so ``errplan fields`` never pays for
ompl, casadi or rerun at start-up. Any :class:`errplan.ErrplanError` becomes one line on stderr
and exit code 2; nothing is written in that case (outputs are written atomically at the end).

Inputs are checked before work starts (:mod:`errplan.inputs`: file decoding, and every size that
follows from the input against the memory the machine can hold). As a last line of defence,
a ``MemoryError``, a ``UnicodeError`` or an ``OSError`` (a file that cannot be read or written)
that still escapes also becomes one line and exit code 2, except a closed stdout (``errplan plan ...
| head -1``): that ends quietly with exit code 141, as for any shell command killed by SIGPIPE; any other exception is a bug in errplan:
one line saying so and exit code 1 (``ERRPLAN_TRACEBACK=1`` shows the traceback). A user never
sees a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from .. import __version__
from ..errors import ErrplanError

CLOSED_PIPE = 141  # exit code when stdout's reader closed the pipe: 128 + SIGPIPE, as a shell reports it
COMMANDS = ("demo", "fields", "plan", "tolerance", "experiment", "calibrate", "view")


def _positive_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a number") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"{s!r}: expected a number > 0")
    return v


def _positive_int(s: str) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not an integer") from None
    if not 1 <= v <= 10**9:
        raise argparse.ArgumentTypeError(f"{s!r}: expected an integer from 1 to 1000000000")
    return v


def check_seed(option: str, value) -> None:
    """A seed given on the command line: an integer from 0 to 2^32 - 1 (numpy and OMPL take it)."""
    if value is not None and not 0 <= value <= 2**32 - 1:
        raise ErrplanError(f"{option} {value}: expected an integer from 0 to 4294967295")


class _OneLineParser(argparse.ArgumentParser):
    """Usage errors are one line on stderr and exit code 2, like every other errplan error."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _OneLineParser(
        prog="errplan",
        description="Plan instrument-tip paths with kinematic-error metrics as costs (Beasley et al.). "
                    "Units are SI (m, rad, s); 'errplan COMMAND --help' lists a command's options.",
    )
    p.add_argument("--version", action="version", version=f"errplan {__version__}",
                   help="print errplan's version and exit")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr (default: progress shown)")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_OneLineParser)

    s = sub.add_parser("demo", help="the bundled scenarios end to end: fields, plan, gains, simulation, recording")
    s.add_argument("--scenario", default=None,
                   help="run only this scenario file, planar or spatial (default: the three bundled scenarios: "
                        "beasley2004_bounded.toml, phantom15_spatial.toml, abdomen.toml)")
    s.add_argument("--record", default="errplan-demo.rrd",
                   help="rerun recording of the planar scenario; the others are written beside it: five files in "
                        "all, <stem>.rrd, <stem>-3d.rrd (the PHANToM), <stem>-abdomen.rrd, <stem>-triad.rrd and "
                        "<stem>-triad-plan.rrd (the setup's triad and planned motions); with --scenario only "
                        "<stem>.rrd (default: %(default)s)")
    s.add_argument("--json", default=None, help="also write the plans as JSON here (default: none)")

    s = sub.add_parser("fields", help="worst-case metric fields of a scenario -> npz")
    s.add_argument("scenario", help="scenario TOML file")
    s.add_argument("--out", required=True, help="npz file to write (required)")
    s.add_argument("--resolution", type=_positive_float, default=None, help="grid spacing, m (default: [fields] resolution)")
    s.add_argument("--rho-star", action="store_true", help="also compute rho_star and k_star, the best achievable contraction (default: off)")
    s.add_argument("--samples", type=int, default=None, help="error-set samples per uncertain axis before refinement (default: [uncertainty] samples)")
    s.add_argument("--metrics", default=None,
                   help="comma-separated subset of G_norm,phi_hat_max,phi_max,rho_star (default: the first three)")
    s.add_argument("--workers", type=int, default=None, help="local worker processes for the grid's tiles (default: all cores)")
    s.add_argument("--scheduler", default=None, help="address of a dask.distributed scheduler to run the tiles on instead, e.g. tcp://host:8786 (default: none, local)")
    s.add_argument("--json", default=None, help="also write the summary as JSON (default: none)")
    s.add_argument("--arm", default=None, help="the arm of a scenario with several instruments, by its [[arm]] name (default: every arm, one F.<arm>.npz each)")

    s = sub.add_parser("plan", help="plan every query, pick gains, simulate planned vs direct")
    s.add_argument("scenario", help="scenario TOML file")
    s.add_argument("--json", default=None, help="plan JSON to write (default: none)")
    s.add_argument("--record", default=None, help="rerun recording (.rrd) to write (default: none)")
    s.add_argument("--query", default=None, help="plan only this query, by name (default: every query)")
    s.add_argument("--iterations", type=_positive_int, default=None,
                   help="the search's budget per query, iterations: it ends there on any machine (default: [planner] iterations)")
    s.add_argument("--time", type=_positive_float, default=None,
                   help="a time cap per query, s: a plan it cuts is flagged and depends on the machine (default: [planner] time, none)")
    s.add_argument("--planner", default=None, help="OMPL planner name (default: [planner] planner)")
    s.add_argument("--seed", type=int, default=None, help="OMPL seed, 0 to 2^32 - 1 (default: [planner] seed)")
    s.add_argument("--arm", default=None, help="the arm of a scenario with several instruments, by its [[arm]] name (default: every query, each with its own arm)")
    s.add_argument("--workers", type=int, default=None,
                   help="local worker processes for the fields' tiles and the queries' gains and simulations "
                        "(default: all cores; the results do not depend on it)")
    s.add_argument("--truth", default=None, metavar="T.toml",
                   help="simulate the planned and direct paths on this scenario's truth (its arm, port and "
                        "[effects]; e.g. calibrate's --export-bench) instead of SCENARIO's (default: SCENARIO's)")

    s = sub.add_parser("tolerance", help="tolerance-design queries of a scenario (port error, tip load, noise, port placement)")
    s.add_argument("scenario", help="scenario TOML file with [[tolerance]] queries")
    s.add_argument("--json", default=None, help="tolerance JSON to write: answers and plot-ready curves (default: none)")
    s.add_argument("--workers", type=int, default=None,
                   help="local worker processes for the port-placement candidates (default: all cores)")
    s.add_argument("--scheduler", default=None,
                   help="address of a dask.distributed scheduler to run the port-placement candidates on instead "
                        "(default: none, local)")
    s.add_argument("--record", default=None, help="rerun recording (.rrd) of the port-placement queries (default: none)")
    s.add_argument("--top", type=int, default=5, help="port-placement candidates listed per query (default: %(default)s)")
    s.add_argument("--arm", default=None, help="the arm of a scenario with several instruments, by its [[arm]] name (default: the setup's triad_placement and setup_placement queries)")
    s.add_argument("--export-scenario", default=None, metavar="OUT.toml",
                   help="write the scenario with the best setup's bases and port estimates (one setup_placement query; "
                        "default: none)")

    s = sub.add_parser("experiment", help="a P1-style bench run on the scenario's truth -> measured-data CSV")
    s.add_argument("scenario", help="scenario TOML file; its [effects] and [sensors] are the bench's truth")
    s.add_argument("--out", required=True, help="measured-data CSV to write (required)")
    s.add_argument("--seed", type=int, default=0, help="seed of the sensor noise (default: %(default)s)")
    s.add_argument("--starts", type=int, default=8,
                   help="start tips: P1's L, M, N where reachable, then spread over the workspace (default: %(default)s)")
    s.add_argument("--max-steps", type=int, default=60, help="commands per run at most (default: %(default)s)")
    s.add_argument("--dwell", type=int, default=10,
                   help="steps recorded after a run first arrives within tolerance (default: %(default)s)")
    s.add_argument("--design", type=int, default=None, metavar="N",
                   help="choose N runs that make the catalogue's parameters identifiable (experiment design) "
                        "instead of --starts x P1's targets, within the default bench's rows (0: as many runs as "
                        "those rows hold); compares with the default bench (default: none, the default bench)")
    s.add_argument("--criterion", default="G", choices=("G", "D", "A", "E"),
                   help="design criterion of the parameters' information (default: %(default)s, see docs/calibration.md)")
    s.add_argument("--separate", default="0.94", metavar="R",
                   help="designed bench: keep every pair of effects below this cross correlation ('none': "
                        "precision only; default: %(default)s)")
    s.add_argument("--max-rows", type=int, default=None,
                   help="designed bench: at most this many rows (default: the default bench's; 0: no limit)")
    s.add_argument("--design-json", default=None,
                   help="also write the design (runs, correlations, sigmas) as JSON (default: none)")
    s.add_argument("--design-effects", default=None, metavar="E1,E2",
                   help="designed bench: the effects whose parameters it makes identifiable, physical, geometric "
                        "(link_length, joint_geometry, instrument_length, tracker_registration) or backlash "
                        "(default: the physical catalogue)")
    s.add_argument("--arm", default=None, help="the arm of a scenario with several instruments, by its [[arm]] name (default: the only arm; required with several)")

    s = sub.add_parser("calibrate", help="close the loop: residual, effect found, error before/after")
    s.add_argument("scenario", help="scenario TOML file: the declared model")
    s.add_argument("data", help="measured-data CSV (errplan experiment writes one)")
    s.add_argument("--validate", default=None,
                   help="held-out CSV for the before/after errors (default: none, the errors on DATA)")
    s.add_argument("--json", default=None, help="calibrate JSON to write (default: none)")
    s.add_argument("--record", default=None, help="rerun recording (.rrd) of the residuals before and after (default: none)")
    s.add_argument("--export-scenario", default=None,
                   help="write the corrected robot: controller and truth both take the found geometry (planar "
                        "link lengths, instrument length, a URDF arm's joint_geometry in a corrected URDF written "
                        "beside it) and the found port; the other effects under [effects] (default: none)")
    s.add_argument("--export-bench", default=None, metavar="F.toml",
                   help="write the bench as it ran: the declared controller unchanged, the fitted effects as its "
                        "truth under [effects] (default: none)")
    s.add_argument("--no-task", action="store_true",
                   help="skip the task before/after (each [[query]] planned on the declared and on the corrected "
                        "model, simulated on the fitted truth: two plans; default: computed when the scenario has queries)")
    s.add_argument("--predictions", default=None,
                   help="CSV of the corrected model's noise-free tracked tip at every row of the validation file "
                        "(the data without one): run, step, tip columns (default: none)")
    s.add_argument("--seed", type=int, default=0, help="seed for the held-out split (default: %(default)s)")
    s.add_argument("--folds", type=int, default=5, help="held-out folds of runs (default: %(default)s)")
    s.add_argument("--effects", default=None,
                   help="comma-separated candidate effects (default: the whole catalogue of docs/physics.md)")
    s.add_argument("--arm", default=None, help="the arm of a scenario with several instruments, by its [[arm]] name (default: the only arm; required with several)")

    s = sub.add_parser("view", help="open a recording in the rerun viewer")
    s.add_argument("recording", help="a .rrd recording written by errplan")
    s.add_argument("--web", action="store_true",
                   help="serve the rerun web viewer (http://localhost:9090) instead of opening the native viewer "
                        "(default: native)")
    return p


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _closed_pipe() -> int:
    """The reader of stdout went away (``errplan plan ... | head -1``): end quietly, as ``cat`` does.

    Whatever is still buffered for stdout goes to the null device, so the interpreter's last flush
    cannot fail again; the exit code is the shell's for a command ended by SIGPIPE (128 + 13)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # stdout without a file descriptor (a test's capture): nothing to redirect
        pass
    return CLOSED_PIPE


def _fail(command: str, message: str) -> None:
    if sys.stderr.isatty():  # clear an updating progress line first
        sys.stderr.write("\r" + " " * 60 + "\r")
    print(f"errplan {command}: error: {_one_line(message)}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except BrokenPipeError:  # errplan --help | head -1
        return _closed_pipe()
    cmd = args.command
    try:
        mod = importlib.import_module(f"errplan.cli.{cmd}")
        if cmd != "view":  # the first run's compile notice names the command (errplan.jit)
            from ..jit import set_label

            set_label(f"errplan {cmd}")
        rc = int(mod.run(args) or 0)
        sys.stdout.flush()  # a reader that stopped early (``| head``) shows here, not at exit
        return rc
    except BrokenPipeError:
        return _closed_pipe()
    except ErrplanError as e:
        _fail(cmd, str(e))
        return 2
    except KeyboardInterrupt:  # pragma: no cover
        print("errplan: interrupted", file=sys.stderr)
        return 130
    except MemoryError as e:  # the input checks should have caught it: still one line, exit 2
        if os.environ.get("ERRPLAN_TRACEBACK"):
            raise
        _fail(cmd, f"out of memory ({e or 'no details'}): an input size is too large for this machine")
        return 2
    except UnicodeError as e:
        if os.environ.get("ERRPLAN_TRACEBACK"):
            raise
        _fail(cmd, f"an input file is not UTF-8 text ({e})")
        return 2
    except OSError as e:
        if os.environ.get("ERRPLAN_TRACEBACK"):
            raise
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        _fail(cmd, f"{where}{e.strerror or e}")
        return 2
    except Exception as e:  # a bug in errplan: say so in one line, no traceback for the user
        if os.environ.get("ERRPLAN_TRACEBACK"):
            raise
        _fail(cmd, f"internal error {type(e).__name__}: {e} (this is a bug in errplan, not in the input; "
                   f"ERRPLAN_TRACEBACK=1 shows the traceback)")
        return 1


def entry() -> None:
    """The ``errplan`` program (the console script and ``python -m errplan``): :func:`main`, then exit
    without the interpreter's cyclic garbage collection of everything still loaded.

    After a command that loaded compiled kernels, that final collection walks numba's type system and
    code objects: about 0.3-0.4 s of a 3 s ``errplan fields``, for memory the process returns to the
    system anyway. The objects are frozen (:func:`gc.freeze`) once the command has returned; the exit
    itself (flushing, ``atexit``, closing files) is as before. Not done by :func:`main`, which tests
    and notebooks call in a process that goes on, nor once OMPL is loaded: its bindings (nanobind) check
    at exit that every object they made was collected, and print a page of "leaked" warnings for the
    frozen ones (``plan``, ``demo``: commands of many seconds, where 0.3 s does not matter)."""
    rc = main()
    if "ompl" not in sys.modules:
        import gc

        gc.freeze()
        gc.disable()
    sys.exit(rc)


if __name__ == "__main__":  # pragma: no cover
    entry()
