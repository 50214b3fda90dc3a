"""``errplan fields SCENARIO --out F.npz [--resolution R] [--rho-star] [--metrics LIST] [--workers N]
[--scheduler ADDRESS]``: planar and spatial scenarios."""
from __future__ import annotations

import math
from pathlib import Path

from ..errors import ErrplanError
from ..report import Progress, format_table, write_json


def field_table(summary: dict, title: str) -> str:
    rows = []
    for name, unit in (("G_norm", "1"), ("phi_hat_max", "deg"), ("phi_max", "deg"), ("rho_star", "1"), ("k_star", "1")):
        s = summary.get(name)
        if s is None:
            continue
        f = (180 / math.pi) if unit == "deg" else 1.0
        rows.append([name, unit, s["min"] * f, s["median"] * f, s["max"] * f])
    if summary.get("clearance") is not None:  # [anatomy]: over the reachable tips
        s = summary["clearance"]
        rows.append(["clearance", "mm", s["min"] * 1000, s["median"] * 1000, s["max"] * 1000])
    lines = [format_table(["field", "unit", "min", "median", "max"], rows, title)]
    grid = " x ".join(str(n) for n in summary["grid"])
    size = (f"{summary['workspace_area_m2'] * 1e4:.1f} cm^2" if "workspace_area_m2" in summary
            else f"{summary['workspace_volume_m3'] * 1e6:.1f} cm^3")
    lines.append(f"workspace: {summary['valid_points']} tips on a {grid} grid at {summary['resolution'] * 1000:g} mm "
                 f"({size})")
    if "blocked_points" in summary:
        lines.append(f"anatomy: {summary['blocked_points']} reachable tips are not robustly clear (outside the workspace); "
                     "clearance over every reachable tip")
    if "share_G_below_1" in summary:
        lines.append(f"share with worst-case ||G|| < 1 (monotonic at the scenario gain): {100 * summary['share_G_below_1']:.1f}%")
    if "share_rho_star_below_1" in summary:
        lines.append(f"share with rho* < 1 (some gain certifies monotonic convergence): {100 * summary['share_rho_star_below_1']:.1f}%")
    return "\n".join(lines)


def run(args) -> int:
    from .. import api
    from ..fields import parse_metrics

    from ..scenario import read_setup
    from . import warmup

    metrics = parse_metrics(args.metrics, args.rho_star)
    if args.workers is not None and args.workers < 1:
        raise ErrplanError(f"--workers {args.workers}: expected a number of worker processes >= 1")
    # A first run of a spatial scenario: its search compiles in a second process while this one loads and
    # checks the arm (its kinematics, its reachability map's build, the anatomy's clearances).
    first = read_setup(args.scenario).arms[0]
    part = warmup.fields_part(first, "phi_max" in metrics) if first.dim == 3 else None
    if part and args.scheduler is None:
        warmup.start((part,))
    st = api.load_setup(args.scenario)
    out = Path(args.out)
    if not out.parent.exists():
        raise ErrplanError(f"--out {args.out}: directory {out.parent} does not exist")
    if args.samples is not None and not 2 <= args.samples <= 41:
        raise ErrplanError(f"--samples {args.samples}: expected an integer from 2 to 41")
    if args.arm is not None or not st.several:
        jobs = [(st.arm(args.arm), out, args.json)]
    else:  # several arms: one npz per arm, F.<arm>.npz
        jobs = [(sc, out.with_name(f"{out.stem}.{n}{out.suffix or '.npz'}"),
                 None if not args.json else str(Path(args.json).with_name(f"{Path(args.json).stem}.{n}"
                                                                          f"{Path(args.json).suffix}")))
                for n, sc in zip(st.arm_names, st.arms)]
    # Progress only on a terminal (an updating line, cleared before any error): an error is then
    # the one line on stderr, also in logs and pipes.
    results = []
    for sc, path, js in jobs:
        prog = Progress("fields", quiet=args.quiet)
        prog.quiet = prog.quiet or not prog.tty
        with prog.cleared_on_error():
            if part:
                warmup.wait(part)
            mf = api.compute_fields(sc, args.resolution, samples=args.samples, progress=prog, metrics=metrics,
                                    workers=args.workers, scheduler=args.scheduler)
            summary = mf.summary()
            if summary["valid_points"] == 0:
                raise ErrplanError(f"{sc.source}: no tip of the grid is reachable under every instance of the error set"
                                   + (f" (arm {sc.name})" if st.several else ""))
        prog.done()
        results.append((sc, path, js, mf, summary))
    for sc, path, js, mf, summary in results:  # written once every arm has its fields: nothing half-written
        mf.save(path)
        if js:
            write_json(js, {"scenario": sc.name, "out": str(path), "summary": summary})
        print(field_table(summary, f"worst-case fields of {sc.name} (gain {sc.controller.gain:g}) -> {path}"))
        if mf.meta.get("noise_worst_case"):  # P2's flexion controller: the worst case over the noise is searched
            print("sensor noise: " + mf.meta["noise_worst_case"])
    return 0
