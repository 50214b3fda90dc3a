"""Benchmark of `errplan calibrate`: time against data size, and what it finds per effect.

    python benchmarks/calibration.py            # timing (1k, 2k, 4k rows) + quality per effect
    python benchmarks/calibration.py --quick    # timing only
    python benchmarks/calibration.py --design   # experiment design only (planar and spatial)
    python benchmarks/calibration.py --spatial  # spatial timing and quality only
    python benchmarks/calibration.py --quality  # the per-effect quality tables only
    python benchmarks/calibration.py --ceiling  # how far any design can lower the sigmas (planar, 3-D)
    python benchmarks/calibration.py --geometry # benches beyond errplan's own model: a UR5 made by
                                                # pinocchio, geometry + gravity, backlash replay, a warp

Timing: bench data on P1's scenario (beasley2004_port.toml, gain 1) with gravity sag undeclared,
more starts for more rows; the whole `calibrate` (noise floor, 22-26 candidates each fitted on all
rows and refitted on 5 folds, selection, structure test, trajectory replays) in-process, best of
one run after a warm-up import. Quality: for each catalogue effect at bench size (and for two
effects, noise only and a 4 mm link-2 length error outside the catalogue) the selection, each
parameter's estimate against the truth in stated sigmas, and the held-out errors before -> after.

Design: the default bench (8 starts x P1's targets) against a designed one with the same number of
rows (``errplan experiment --design``): largest correlations and condition numbers predicted for
all catalogue parameters, the criteria compared, then real benches (the same truth, default vs
designed runs) calibrated against the declared scenario: what is selected and the recovered
parameters' stated sigmas.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from errplan.calibration import calibrate  # noqa: E402
from errplan.experiment import run_experiment  # noqa: E402
from errplan.report import format_table  # noqa: E402
from errplan.scenario import Robot  # noqa: E402
from errplan.api import load_scenario
from errplan.simulation import Plant  # noqa: E402
from errplan.models import build_arm

PORT = ROOT / "scenarios" / "beasley2004_port.toml"
GRAVITY = {"gravity_sag": {"c1": 0.004, "c2": 0.002, "c3": 0.003}}
CASES = [
    ("port_offset", {"port_offset": {"dy": 0.003, "dz": -0.002}}),
    ("joint_offset", {"joint_offset": {"dq1": 0.003, "dq2": -0.002}}),
    ("tracker_offset", {"tracker_offset": {"by": 0.002, "bz": -0.0015}}),
    ("gravity_sag", GRAVITY),
    ("shaft_flexion", {"shaft_flexion": {"fy": 2.0, "fz": 1.0}}),
    ("port_friction", {"port_friction": {"fa": 0.0015, "fn": 0.001}}),
    ("gravity+friction", {**GRAVITY, "port_friction": {"fa": 0.001, "fn": 0.0008}}),
    ("noise only", {}),
    ("link 2 +4 mm (changed robot)", None),
    # geometry (physics.md "Closing the loop when the catalogue lacks the effect")
    ("link_length", {"link_length": {"dl1": 0.003, "dl2": -0.002}}),
    ("instrument_length", {"instrument_length": {"dL": 0.004}}),
    ("tracker_registration", {"tracker_registration": {"rx": 0.014, "by": 0.001, "bz": -0.001}}),
    ("tracker scale 1.5 % (outside)", "scaled_tracker"),
]


def timing(sc) -> None:
    truth = sc.with_(effects=GRAVITY)
    rows = []
    for starts, dwell in ((8, 10), (16, 10), (22, 16)):
        d = run_experiment(truth, seed=1, n_starts=starts, dwell=dwell).data
        t0 = time.perf_counter()
        rep = calibrate(sc, d, seed=0)
        dt = time.perf_counter() - t0
        rows.append([d.rows, d.runs, len(rep.candidates), ", ".join(rep.selected) or "none", dt])
    print(format_table(["rows", "runs", "candidates", "selected", "calibrate s"], rows,
                       "calibrate time against data size (P1 scenario, gravity sag undeclared)"))


def _wrong_link(sc):
    """A plant whose second link is 4 mm longer than declared: an effect in no catalogue (planar)."""
    r = sc.robot
    wrong = sc.with_(robot=Robot(r.base, (r.link_lengths[0], r.link_lengths[1] + 0.004), r.home_angles,
                                 r.joint_limits, r.joint_sum_limits))
    return Plant.from_model(build_arm(wrong), noise=True)


def _long_shaft(sc):
    """A plant whose shaft is 4 mm longer than declared: an effect in no catalogue (3-D)."""
    from errplan.experiment import truth_plant

    return truth_plant(sc).with_(length=sc.instrument.length + 0.004)


def _scaled_tracker(sc, scale=0.015, centre=(0.0, 0.30)):
    """A tracker whose scale is off by 1.5 % about a point: an effect in no catalogue (planar)."""
    import numpy as np
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class Scaled(Plant):
        def tip(self, q_enc, u=None):
            t = super().tip(q_enc, u)
            return t + scale * (t - np.asarray(centre))

    base = Plant.from_model(build_arm(sc), noise=True)
    return Scaled(**{f: getattr(base, f) for f in base.__dataclass_fields__})


def quality(sc, cases, unmodelled, label: str, units: str) -> None:
    """Per effect of ``cases`` (None: ``unmodelled(sc)``'s plant, an effect in no catalogue): what
    calibrate selects, the errors before and after on a held-out run, and every parameter's z-score."""
    rows, prow = [], []
    for name, eff in cases:
        if eff is None or eff == "scaled_tracker":
            plant = unmodelled(sc) if eff is None else _scaled_tracker(sc)
            data = run_experiment(sc, seed=11, plant=plant).data
            val = run_experiment(sc, seed=12, plant=plant).data
            eff = {}
        else:
            data = run_experiment(sc.with_(effects=eff), seed=11).data
            val = run_experiment(sc.with_(effects=eff), seed=12).data
        rep = calibrate(sc, data, validate=val, seed=0)
        e = rep.errors
        rows.append([name, ", ".join(rep.selected) or "none", "yes" if rep.explained else "NO", rep.noise.sigma * 1e3,
                     e.pose_before * 1e3, e.pose_after * 1e3, e.trajectory_before * 1e3, e.trajectory_after * 1e3,
                     e.trajectory_after / e.trajectory_before])
        for ef, ps in rep.parameters.items():
            for p, v in ps.items():
                true = eff.get(ef, {}).get(p, 0.0)
                if v is None:
                    prow.append([name, f"{ef}.{p}", true, "not identifiable", "", ""])
                    continue
                s = rep.uncertainty[ef][p]
                if s is None:  # a geometric group's parameter the rows do not need: held at 0
                    prow.append([name, f"{ef}.{p}", true * 1e3, "0 (not needed)", "", ""])
                    continue
                if ef == "joint_geometry":
                    prow.append([name, f"{ef}.{p}", true * 1e3, v * 1e3, s * 1e3, "(base parameter)"])
                    continue
                f = 1.0 if ef == "shaft_flexion" else 1e3
                prow.append([name, f"{ef}.{p}", true * f, v * f, s * f, (v - true) / s])
    print(format_table(["truth", "selected", "explained", "noise mm", "pose before", "pose after", "traj before",
                        "traj after", "traj ratio"], rows,
                       f"{label}, per effect (held-out validation run; errors in mm, RMS per coordinate)"))
    print()
    print(format_table(["truth", "parameter", "true", "estimate", "sigma", "z"], prow,
                       f"{label}, parameters ({units}): estimate - true in stated sigmas"))


DESIGN_TRUTHS = [
    ("joint_offset + gravity_sag", {"joint_offset": {"dq1": 0.003, "dq2": -0.002}, **GRAVITY}),
    ("port_offset + shaft_flexion", {"port_offset": {"dy": 0.003, "dz": -0.002}, "shaft_flexion": {"fy": 2.0, "fz": 1.0}}),
    ("gravity_sag", GRAVITY),
    ("port_offset", {"port_offset": {"dy": 0.003, "dz": -0.002}}),
    ("shaft_flexion", {"shaft_flexion": {"fy": 2.0, "fz": 1.0}}),
    ("joint_offset", {"joint_offset": {"dq1": 0.003, "dq2": -0.002}}),
]


def design(sc, truths=DESIGN_TRUTHS, label="P1 scenario") -> None:
    import numpy as np

    from errplan.calibration.design import CRITERIA, design_experiment

    t0 = time.perf_counter()
    dz = design_experiment(sc, None)
    t_design = time.perf_counter() - t0
    print(dz.text().split("\n\npredicted")[0])
    print(f"design time {t_design:.1f} s ({dz.candidates} candidate runs); predicted mean sigma ratio (all parameters "
          f"fitted together) {dz.sigma_ratio():.2f}")
    print()
    crow = []
    for c in CRITERIA:
        for sep in (None, 0.94):
            d = dz if (c == "G" and sep == 0.94) else design_experiment(sc, None, criterion=c, separate=sep)
            conf = [f"{a}+{b} {c1:.3f}" for a, b, c0, c1 in d.confused()]
            crow.append([c, "-" if sep is None else f"< {sep:g}", d.designed.runs, d.designed.rows,
                         d.designed.largest_correlation()[0], d.designed.condition(), "; ".join(conf),
                         d.sigma_ratio()])
    print(format_table(["criterion", "pairs", "runs", "rows", "largest corr", "cond", "confused pairs (designed)",
                        "sigma ratio"], crow, f"design criteria compared ({label}, predicted)"))
    print()
    rows, ratios = [], []
    for name, eff in truths:
        truth = sc.with_(effects=eff)
        out = {}
        for bench, runs in (("default", None), ("designed", dz.runs)):
            data = run_experiment(truth, seed=11, runs=runs).data
            rep = calibrate(sc, data, seed=0)
            out[bench] = rep
        r0, r1 = out["default"], out["designed"]
        for ef, ps in eff.items():
            for p_, v in ps.items():
                s0 = r0.uncertainty.get(ef, {}).get(p_) if ef in r0.parameters else None
                s1 = r1.uncertainty.get(ef, {}).get(p_) if ef in r1.parameters else None
                e0 = r0.parameters.get(ef, {}).get(p_)
                e1 = r1.parameters.get(ef, {}).get(p_)
                ratio = s1 / s0 if s0 and s1 else float("nan")
                if np.isfinite(ratio):
                    ratios.append(ratio)
                f = 1.0 if ef == "shaft_flexion" else 1e3
                rows.append([name, f"{ef}.{p_}", v * f,
                             f"{e0 * f:.4g} ± {s0 * f:.3g}" if s0 else "not selected",
                             f"{e1 * f:.4g} ± {s1 * f:.3g}" if s1 else "not selected", ratio])
        rows.append([name, "selected", "", ", ".join(r0.selected) or "none", ", ".join(r1.selected) or "none",
                     f"rows {r0.fit_errors.rows} / {r1.fit_errors.rows}"])
    print(format_table(["truth", "parameter", "true", "default bench", "designed bench", "sigma ratio"], rows,
                       f"calibration on real benches ({label}; mm, mrad or 1/m^2; same seed)"))
    print(f"mean sigma ratio designed / default over the recovered parameters: {np.mean(ratios):.2f}")


SPATIAL = ROOT / "scenarios" / "phantom15_spatial.toml"
SPATIAL_GRAVITY = {"gravity_sag": {"c1": 0.0, "c2": 0.05, "c3": 0.08}}
SPATIAL_CASES = [
    ("port_offset", {"port_offset": {"dx": 0.002, "dy": 0.003, "dz": -0.002}}),
    ("joint_offset", {"joint_offset": {"dq1": 0.003, "dq2": -0.002, "dq3": 0.002}}),
    ("tracker_offset", {"tracker_offset": {"bx": 0.001, "by": 0.002, "bz": -0.0015}}),
    ("gravity_sag", SPATIAL_GRAVITY),
    ("shaft_flexion", {"shaft_flexion": {"fx": 1.0, "fy": 2.0, "fz": 0.5}}),
    ("port_friction", {"port_friction": {"fa": 0.0015, "fn": 0.001}}),
    ("gravity+friction", {**SPATIAL_GRAVITY, "port_friction": {"fa": 0.001, "fn": 0.0008}}),
    ("noise only", {}),
    ("shaft +4 mm (changed length)", None),
    ("joint_geometry", {"joint_geometry": {"dy_2": 0.002, "rz_2": 0.008, "dx_3": 0.002, "dz_3": 0.003,
                                           "rx_3": 0.010}}),
    ("tracker_registration", {"tracker_registration": {"rx": 0.008, "ry": -0.010, "rz": 0.006, "bx": 0.001,
                                                       "by": 0.0, "bz": -0.001}}),
]
SPATIAL_DESIGN_TRUTHS = [
    ("joint_offset + gravity_sag", {"joint_offset": {"dq1": 0.003, "dq2": -0.002, "dq3": 0.002}, **SPATIAL_GRAVITY}),
    ("port_offset + shaft_flexion", {"port_offset": {"dx": 0.002, "dy": 0.003, "dz": -0.002},
                                     "shaft_flexion": {"fx": 1.0, "fy": 2.0, "fz": 0.5}}),
    ("gravity_sag", SPATIAL_GRAVITY),
    ("port_offset", {"port_offset": {"dx": 0.002, "dy": 0.003, "dz": -0.002}}),
    ("shaft_flexion", {"shaft_flexion": {"fx": 1.0, "fy": 2.0, "fz": 0.5}}),
    ("joint_offset", {"joint_offset": {"dq1": 0.003, "dq2": -0.002, "dq3": 0.002}}),
]


def spatial_scenario():
    """The spatial bench: the bundled PHANToM with a waist, its controller's port estimate
    (8, 4, 8) mm off and gain 0.3 (so that the paths have several steps for the replay to follow)."""
    from dataclasses import replace

    sc = load_scenario(SPATIAL)
    return sc.with_(port=replace(sc.port, estimate=(0.008, 0.004, 0.168)),
                    controller=replace(sc.controller, gain=0.3), name="phantom15-bench")


def spatial_timing(sc) -> None:
    from errplan.experiment import read_measured_csv

    truth = sc.with_(effects=SPATIAL_GRAVITY)
    rows = []
    for starts in (8, 14):
        d = run_experiment(truth, seed=1, n_starts=starts).data
        t0 = time.perf_counter()
        rep = calibrate(sc, d, seed=0)
        dt = time.perf_counter() - t0
        rows.append([d.rows, d.runs, len(rep.candidates), ", ".join(rep.selected) or "none", dt])
    # the whole command on a file: reading, calibrating, JSON and corrected scenario
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        toml = Path(tmp) / "declared.toml"
        text = SPATIAL.read_text(encoding="utf-8").replace('urdf = "phantom15.urdf"', f'urdf = "{ROOT / "scenarios" / "phantom15.urdf"}"')
        text = text.replace("estimate = [0.0, 0.0, 0.160]", "estimate = [0.008, 0.004, 0.168]").replace("gain = 1.0", "gain = 0.3")
        toml.write_text(text, encoding="utf-8")
        d.source = str(Path(tmp) / "bench.csv")
        d.write_csv(d.source)
        assert read_measured_csv(d.source, load_scenario(toml)).rows == d.rows
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "errplan", "-q", "calibrate", str(toml), d.source, "--json",
                        str(Path(tmp) / "c.json"), "--export-scenario", str(Path(tmp) / "c.toml")], check=True,
                       stdout=subprocess.DEVNULL)
        rows.append([d.rows, d.runs, "CLI", "(whole command, --json --export-scenario)", time.perf_counter() - t0])
    print(format_table(["rows", "runs", "candidates", "selected", "calibrate s"], rows,
                       "spatial calibrate time (PHANToM with a waist, gravity sag undeclared; target 60 s for 4,000 rows)"))


# ----------------------------------------------------------------------------- the design's ceiling
def _logvars(Ms, idx):
    """log of the marginal variances (k, len(idx)) of the parameters ``idx`` fitted together."""
    import numpy as np

    S = Ms[:, idx][:, :, idx]
    dg = np.sqrt(np.maximum(np.abs(np.diagonal(S, axis1=1, axis2=2)), 1e-300))
    Sn = S / (dg[:, :, None] * dg[:, None, :])
    sign, ld = np.linalg.slogdet(Sn)
    ok = (sign > 0) & (ld > np.log(1e-24))
    V = np.linalg.inv(np.where(ok[:, None, None], Sn, np.eye(len(idx))))
    dv = np.diagonal(V, axis1=1, axis2=2) / dg ** 2
    return np.where(ok[:, None] & (dv > 0), np.log(np.maximum(dv, 1e-300)), np.inf)


class SigmaObjective:
    """A design objective aimed straight at the reported sigmas: minus the log of the mean, over the
    parameters of ``models`` (each a list of parameter indices fitted together), of designed /
    default sigma; with the design module's separation penalty. Duck-types
    errplan.calibration.design.Objective for ``select_runs``."""

    def __init__(self, models, M0, pairs, separate):
        self.models, self.M0, self.pairs, self.separate = models, M0, tuple(pairs), separate
        self.ref = [_logvars(M0[None], m)[0] for m in models]

    def watching(self, M, margin=0.15):
        from errplan.calibration.design import pair_correlations

        if self.separate is None:
            return self
        rho = pair_correlations(M[None], list(self.pairs))[0]
        out = SigmaObjective.__new__(SigmaObjective)
        out.__dict__.update(self.__dict__, pairs=tuple(p for p, r in zip(self.pairs, rho) if r > self.separate - 0.15))
        return out

    def __call__(self, Ms):
        import numpy as np

        from errplan.calibration.design import pair_correlations

        r = np.concatenate([np.exp(0.5 * (_logvars(Ms, m) - r0)) for m, r0 in zip(self.models, self.ref)], axis=1)
        with np.errstate(invalid="ignore"):
            s = -np.log(r.mean(axis=1))
        s = np.where(np.isfinite(s), s, -np.inf)
        if self.separate is not None and self.pairs:
            rho = np.clip(pair_correlations(Ms, list(self.pairs)), 0.0, 1.0 - 1e-12)
            s = s + 50.0 * np.minimum(np.log1p(-rho ** 2) - np.log1p(-self.separate ** 2), 0.0).sum(axis=1)
        return s


def ceiling(sc, label, dense=None) -> None:
    """How far any design can lower the sigmas with the default bench's rows: per-row information
    of the best candidate runs, and designs that optimise the reported sigmas directly."""
    import itertools

    import numpy as np

    from errplan.calibration import design as D
    from errplan.experiment import DEFAULT_STARTS, choose_starts, target_offsets

    model = D.catalogue_model(sc)
    S = choose_starts(sc, DEFAULT_STARTS)
    offs = target_offsets(dim=sc.dim)
    runs0 = np.stack([np.repeat(S, len(offs), axis=0), (S[:, None] + offs[None]).reshape(-1, sc.dim)], axis=1)
    d0, _ = D.predict_runs(sc, runs0)
    info0 = D.bench_info(sc, d0, model)
    M0, eff = info0.M, info0.effects
    names = list(eff)
    pairs = [(tuple(eff[a]), tuple(eff[b])) for a, b in itertools.combinations(names, 2)]
    rho0 = D.pair_correlations(M0[None], pairs)[0]
    confused = [list(a) + list(b) for (a, b), r in zip(pairs, rho0) if r > D.CONFUSED]
    singles = [list(eff[a]) for a in names]
    every = [list(range(M0.shape[0]))]
    sets = [("default candidates", {})] + ([("dense candidates", dense)] if dense else [])
    for cname, kw in sets:
        cand = D.candidate_runs(sc, **kw)
        data, _ = D.predict_runs(sc, cand, seed=1)
        data = data.subset(np.flatnonzero(D.arrived(data, max(5e-4, 3 * sc.sensors.tracker_sigma))))
        blocks = D.run_blocks(D.row_jacobian(sc, data, model), data)
        rows = data.lengths
        if cname == "default candidates":
            prow = []
            for e in names:
                i = eff[e]
                per = np.trace(blocks[:, i][:, :, i], axis1=1, axis2=2) / rows
                ref = np.trace(M0[np.ix_(i, i)]) / info0.rows
                prow.append([e, f"{per.max() / ref:.2f}", f"{np.percentile(per, 90) / ref:.2f}", f"{np.median(per) / ref:.2f}"])
            print(format_table(["effect", "best run", "90th percentile", "median"], prow,
                               f"{label}: information per row of the candidate runs (trace of the effect's block) "
                               "relative to the default bench's mean"))
            print()
        out = []
        objectives = [("G (errplan's default)", D.Objective("G", tuple(pairs), D.SEPARATE)),
                      ("each effect alone", SigmaObjective(singles, M0, pairs, None)),
                      ("each effect alone", SigmaObjective(singles, M0, pairs, D.SEPARATE)),
                      ("the confused pairs' fits", SigmaObjective(confused, M0, pairs, D.SEPARATE)),
                      ("all parameters together", SigmaObjective(every, M0, pairs, D.SEPARATE))]
        for oname, obj in objectives:
            ch = D.select_runs(blocks, rows, None, max_rows=info0.rows, objective=obj)
            M = blocks[ch].sum(axis=0)

            def ratio(models, M=M):
                return float(np.mean(np.concatenate([np.exp(0.5 * (_logvars(M[None], m)[0] - _logvars(M0[None], m)[0]))
                                                     for m in models])))
            rho1 = D.pair_correlations(M[None], pairs)[0]
            worst = max(r1 for r0, r1 in zip(rho0, rho1) if r0 > D.CONFUSED)
            out.append([oname, "-" if getattr(obj, "separate", None) is None else f"< {D.SEPARATE:g}", len(rows),
                        int(rows[ch].sum()), ratio(singles), ratio(confused), ratio(every), worst])
        print(format_table(["design optimises the sigma of", "pairs", "candidates", "rows", "each effect alone",
                            "confused pairs fitted", "all fitted together", "worst confused pair after"], out,
                           f"{label}, {cname}: mean designed / default sigma (predicted, same rows as the default "
                           f"bench, {info0.rows})"))
        print()


def _ur5_longer_upper_arm(extra: float = 0.003):
    """The UR5 scenario and a plant made by pinocchio from example-robot-data's URDF with the upper arm
    ``extra`` m longer (the elbow joint's origin): errplan's joint_geometry plays no part in it."""
    import tempfile

    from errplan.kinematics.urdf import UrdfArm
    from errplan.packages import resolve_package_uri

    sc = load_scenario(ROOT / "scenarios" / "ur5_port.toml")
    r = sc.robot
    text = resolve_package_uri("package://ur_description/urdf/ur5_joint_limited_robot.urdf").read_text()
    old = '<origin rpy="0.0 0.0 0.0" xyz="0.0 -0.1197 0.425"/>'
    path = Path(tempfile.mkdtemp()) / "ur5_longer.urdf"
    path.write_text(text.replace(old, old.replace("0.425", repr(0.425 + extra))))
    arm = UrdfArm.load(path, r.joints, r.wrist, base_position=r.base_position, base_rpy=r.base_rpy,
                       joint_limits=r.joint_limits, coupled_limits=r.coupled_limits or ())
    return sc, Plant(arm, sc.instrument.length, tuple(sc.port.position), tracker_sigma=sc.sensors.tracker_sigma)


def _warp_plant(sc):
    """P1's arm seen through a smooth cubic distortion of the tracker's space (outside every catalogue)."""
    from dataclasses import dataclass

    import numpy as np

    @dataclass(frozen=True)
    class Warp(Plant):
        def tracked(self, tip):
            t = super().tracked(tip)
            z = (t - np.array([0.0, 0.36])) / 0.08
            return t + 0.0006 * np.stack([z[..., 0] ** 3 - z[..., 1] ** 2 * z[..., 0],
                                          z[..., 1] ** 3 + 0.5 * z[..., 0] ** 2], -1)

    base = Plant.from_model(build_arm(sc), noise=True)
    return Warp(**{f: getattr(base, f) for f in base.__dataclass_fields__})


def geometry(sc) -> None:
    """Benches beyond errplan's own model: what calibrate selects, whether it says explained, and the
    validation errors before -> after (pose; every-step controller replay); for the UR5 the largest
    held-out prediction error against the done-when tolerance; for the warp the empirical term."""
    import numpy as np

    from errplan.calibration import declared_plant, motion_model
    from errplan.effects import predict_tracked
    from errplan.experiment import truth_plant

    rows = []
    ur5, ur5_plant = _ur5_longer_upper_arm()
    cases = [
        ("UR5, upper arm +3 mm (pinocchio)", ur5, ur5_plant, 2, 1),
        ("P1, links +3/-2 mm + gravity sag", sc.with_(effects={"link_length": {"dl1": 0.003, "dl2": -0.002}, **GRAVITY}),
         None, 5, 3),
        ("P1, backlash 1.5 mrad per joint", sc.with_(effects={"backlash": {"b1": 0.0015, "b2": 0.0015}}), None, 5, 3),
        ("P1, cubic tracker distortion", sc, _warp_plant(sc), 5, 5),
    ]
    for label, truth_sc, plant, n_fit, n_val in cases:
        decl = sc if truth_sc is not ur5 and plant is None else truth_sc
        decl = decl.with_(effects={}) if plant is None else decl
        t0 = time.perf_counter()
        data = run_experiment(truth_sc, seed=71, n_starts=n_fit, plant=plant).data
        val = run_experiment(truth_sc, seed=72, n_starts=n_val, plant=plant).data
        rep = calibrate(decl, data, validate=val, seed=0)
        dt = time.perf_counter() - t0
        v = rep.validation_errors
        pars = "; ".join(f"{e}: " + ", ".join(f"{p}={x * 1e3:+.3g}" for p, x in list(ps.items())[:3])
                         + (" ..." if len(ps) > 3 else "") for e, ps in rep.parameters.items())
        extra = ""
        if truth_sc is ur5:
            tp = plant
            u = np.zeros_like(val.tip)
            true = tp.tracked(tp.tip(val.q, u))
            dec = truth_plant(decl, effects=False, noise=False)
            pred = rep.model.predict(dec, val.q, u)
            tol = np.maximum(5e-5, 0.02 * np.abs(dec.tracked(dec.tip(val.q, u)) - true))
            extra = f"worst |pred - true| / tol = {np.max(np.abs(pred - true) / tol):.2f}"
        if rep.empirical is not None:
            em = rep.empirical
            extra = (f"empirical: {len(em['terms'])} terms, validation {em['validation_rms_declared'] * 1e3:.3f} -> "
                     f"{em['validation_rms_with_term'] * 1e3:.3f} mm")
            if plant is not None and truth_sc is sc:
                u = val.commanded_directions(motion_model(sc))
                true = plant.tracked(plant.tip(val.q, u))
                dp = declared_plant(sc)
                x_sel = predict_tracked(rep.model.plant(dp), val.q, u, val.run)
                x_emp = x_sel + rep.empirical_predict(x_sel, val.q)
                err = lambda x: float(np.sqrt(np.mean((x - true) ** 2)))  # noqa: E731
                extra += (f"; noise-free error declared {err(predict_tracked(dp, val.q, u, val.run)) * 1e3:.3f} -> "
                          f"with term {err(x_emp) * 1e3:.3f} mm")
        rows.append([label, "+".join(rep.selected) or "none", "yes" if rep.explained else "no", pars,
                     f"{v.pose_before * 1e3:.3f} -> {v.pose_after * 1e3:.3f}",
                     f"{v.trajectory_all_before * 1e3:.3f} -> {v.trajectory_all_after * 1e3:.3f}", extra, f"{dt:.0f}"])
    print(format_table(["bench", "selected", "explained", "parameters (mm, mrad)", "pose mm", "replay, every step mm",
                        "", "s"], rows, "benches beyond errplan's own model (validation errors before -> after)"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="timing only")
    ap.add_argument("--design", action="store_true", help="experiment design only")
    ap.add_argument("--spatial", action="store_true", help="spatial rows only")
    ap.add_argument("--quality", action="store_true", help="the per-effect quality tables only (planar and spatial)")
    ap.add_argument("--ceiling", action="store_true",
                    help="how far any design can lower the sigmas with the default bench's rows")
    ap.add_argument("--geometry", action="store_true",
                    help="benches beyond errplan's own model (a UR5 made by pinocchio, geometry + gravity, backlash, a warp)")
    args = ap.parse_args()
    sc = load_scenario(PORT)
    if args.geometry:
        geometry(sc)
        return 0
    if args.ceiling:
        ceiling(sc, "P1 scenario", dense={"spacing": 0.005, "distances": (0.02, 0.04, 0.07), "max_starts": 2000})
        ceiling(spatial_scenario(), "PHANToM bench, 3-D")
        return 0
    if args.design:
        design(sc)
        print()
        design(spatial_scenario(), SPATIAL_DESIGN_TRUTHS, "PHANToM bench, 3-D")
        return 0
    if args.quality:
        quality(sc, CASES, _wrong_link, "P1 scenario, 8 starts", "mm, mrad or 1/m^2")
        print()
        quality(spatial_scenario(), SPATIAL_CASES, _long_shaft, "spatial (PHANToM bench, 8 starts x 14 targets)",
                "mm, mrad, mrad/(N m) or 1/m^2")
        return 0
    if args.spatial:
        sp = spatial_scenario()
        spatial_timing(sp)
        print()
        quality(sp, SPATIAL_CASES, _long_shaft, "spatial (PHANToM bench, 8 starts x 14 targets)",
                "mm, mrad, mrad/(N m) or 1/m^2")
        return 0
    calibrate(sc, run_experiment(sc, seed=0, n_starts=2).data)  # warm-up: imports, caches
    timing(sc)
    sp = spatial_scenario()
    print()
    spatial_timing(sp)
    if not args.quick:
        print()
        quality(sc, CASES, _wrong_link, "P1 scenario, 8 starts", "mm, mrad or 1/m^2")
        print()
        quality(sp, SPATIAL_CASES, _long_shaft, "spatial (PHANToM bench, 8 starts x 14 targets)",
                "mm, mrad, mrad/(N m) or 1/m^2")
    return 0


if __name__ == "__main__":
    sys.exit(main())
