"""What a newcomer trips on in the first hour, each checked the way the newcomer met it: advice that must
work when followed, a unit slip that must be named, a notice that must tell the truth, a pipe closed by
``head``, a run status that must show beside a clearance, and links and times in the documentation that
must agree with the repository as committed."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import errplan
from errplan.api import parse_scenario
from errplan.cli import CLOSED_PIPE, main
from errplan.errors import InfeasibleError

ROOT = Path(__file__).resolve().parents[1]
PORT = ROOT / "scenarios" / "beasley2004_port.toml"
SPATIAL = ROOT / "scenarios" / "phantom15_spatial.toml"
NODULE = ([0.0, -0.08, 0.35], 0.007)


# ----------------------------------------------------------------------------- advice that works
def nodule_scenario(goal) -> errplan.Scenario:
    """The PHANToM 1.5 with a spherical nodule in a small task region (a coarse grid: a cheap field)."""
    doc = tomllib.loads(SPATIAL.read_text(encoding="utf-8"))
    doc["robot"]["urdf"] = str(ROOT / "scenarios" / "phantom15.urdf")
    doc["fields"].update(resolution=0.008, region={"x": [-0.08, 0.08], "y": [-0.12, -0.04], "z": [0.30, 0.40]})
    doc["anatomy"] = {"clearance": 0.003,
                      "obstacle": [{"name": "nodule", "shape": "sphere", "center": NODULE[0], "radius": NODULE[1]}]}
    doc["query"] = [{"name": "past-nodule", "start": [-0.07, -0.08, 0.35], "goal": list(goal)}]
    return parse_scenario(doc, str(ROOT / "scenarios" / "nodule.toml"))


def shaft_clearance(port_box, tip, centre, radius) -> float:
    """Smallest distance (m) from the shaft [port, tip] to the sphere over the port box's corners (closed
    form; the distance to a sphere is smallest at a corner of the box only approximately, so this is an
    upper bound of the robust clearance: enough to show a refused tip is too close)."""
    tip, c = np.asarray(tip, float), np.asarray(centre, float)
    best = np.inf
    for port in port_box:
        u = tip - port
        t = np.clip(np.dot(c - port, u) / np.dot(u, u), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(port + t * u - c)) - radius)
    return best


def test_the_suggested_tip_pasted_as_the_goal_plans():
    """A goal too close to the nodule is refused with a suggestion; that suggestion, exactly as printed,
    pasted in as the goal, plans (the search, the gains' endpoint check and the simulations)."""
    bad = [0.0, -0.08, 0.361]  # 4 mm above the nodule's centre: the shaft passes through it
    sc = nodule_scenario(bad)
    corners = [np.array(sc.port.estimate) + np.array([dx, dy, dz]) for dx in (-0.005, 0.005)
               for dy in (-0.005, 0.005) for dz in (-0.005, 0.005)]
    assert shaft_clearance(corners, bad, *NODULE) < 0.003  # independent: the refusal is right
    with pytest.raises(InfeasibleError, match="the nearest usable tip is") as e:
        errplan.plan(sc, query="past-nodule")
    m = re.search(r"the nearest usable tip is \[([^\]]+)\] m, ([0-9.]+) mm away", str(e.value))
    tip = [float(v) for v in m.group(1).split(",")]
    assert float(m.group(2)) > 0 and abs(np.linalg.norm(np.subtract(tip, bad)) * 1000 - float(m.group(2))) < 0.06
    result = errplan.plan(nodule_scenario(tip), query="past-nodule")  # raises if refused again
    (q,) = result.queries
    assert np.allclose(q.planned.path[-1], tip) and q.planned.valid


# ----------------------------------------------------------------------------- unit slips
def _write(tmp_path, text: str) -> Path:
    p = tmp_path / "s.toml"
    p.write_text(text, encoding="utf-8")
    return p


@pytest.mark.parametrize("edit,key,hint", [
    (("length = 0.320", "length = 320"), "[instrument] length = 320", "write 0.32"),
    (("link_lengths = [0.210, 0.210]", "link_lengths = [210, 210]"), "[robot] link_lengths", "write 0.21"),
], ids=["instrument-mm", "links-mm"])
def test_millimetres_for_metres_are_named(tmp_path, capsys, edit, key, hint):
    text = PORT.read_text(encoding="utf-8")
    assert edit[0] in text
    s = _write(tmp_path, text.replace(edit[0], edit[1]))
    rc = main(["-q", "plan", str(s), "--json", str(tmp_path / "p.json")])
    err = capsys.readouterr().err
    assert rc == 2 and key in err and "millimetres" in err and hint in err, err
    assert err.count("\n") == 1 and sorted(os.listdir(tmp_path)) == ["s.toml"]


def test_degrees_for_radians_are_named(tmp_path, capsys):
    text = SPATIAL.read_text(encoding="utf-8").replace('urdf = "phantom15.urdf"',
                                                        f'urdf = "{ROOT / "scenarios" / "phantom15.urdf"}"')
    assert "base_rpy = [0.0, 0.0, 0.0]" in text
    s = _write(tmp_path, text.replace("base_rpy = [0.0, 0.0, 0.0]", "base_rpy = [-90, 0, 0]"))
    rc = main(["-q", "fields", str(s), "--out", str(tmp_path / "f.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and "[robot] base_rpy" in err and "degrees" in err and "-1.5708" in err, err
    assert sorted(os.listdir(tmp_path)) == ["s.toml"]


def test_legitimate_values_still_load():
    """The bounds leave real values alone: a base turned by a full turn (written to 4 decimals), joint
    limits of a full turn each way."""
    doc = tomllib.loads(SPATIAL.read_text(encoding="utf-8"))
    doc["robot"]["urdf"] = str(ROOT / "scenarios" / "phantom15.urdf")
    doc["robot"]["base_rpy"] = [0.0, 0.0, 6.2832]
    sc = parse_scenario(doc, str(ROOT / "scenarios" / "x.toml"))
    assert sc.robot.base_rpy[2] == 6.2832
    doc = tomllib.loads(PORT.read_text(encoding="utf-8"))
    doc["robot"]["joint_limits"] = [[-6.2832, 6.2832], [-6.2832, 6.2832]]
    assert parse_scenario(doc, str(PORT)).robot.joint_limits[0] == (-6.2832, 6.2832)


# ----------------------------------------------------------------------------- a closed pipe
def test_a_closed_pipe_ends_quietly(tmp_path):
    """``errplan fields ... | head -1``: the reader is gone before errplan prints its table; errplan ends
    without an error line (exit 141, as a shell reports a command ended by SIGPIPE), and the npz it was
    asked for is written (the work was done)."""
    env = dict(os.environ, ERRPLAN_COMPILE_NOTICE="0", ERRPLAN_WARMUP="0")
    p = subprocess.Popen([sys.executable, "-m", "errplan", "-q", "fields", str(PORT), "--out", str(tmp_path / "f.npz"),
                          "--resolution", "0.02", "--metrics", "G_norm", "--workers", "1"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=tmp_path)
    p.stdout.close()  # head -1 gone before the first line
    err = p.stderr.read().decode()
    rc = p.wait(timeout=600)
    assert rc == CLOSED_PIPE and err == "", (rc, err)


def test_a_closed_pipe_in_process(tmp_path, capsys, monkeypatch):
    """The same for every command, in process: a stdout whose writes fail with EPIPE."""
    class Closed:
        def write(self, s):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            raise BrokenPipeError(32, "Broken pipe")

        def fileno(self):
            raise ValueError("no descriptor")

    monkeypatch.setattr(sys, "stdout", Closed())
    rc = main(["-q", "fields", str(PORT), "--out", str(tmp_path / "f.npz"), "--resolution", "0.02", "--metrics",
               "G_norm", "--workers", "1"])
    monkeypatch.undo()
    assert rc == CLOSED_PIPE and capsys.readouterr().err == ""


# ----------------------------------------------------------------------------- a failure beside its clearance
def _run(status_direct: str, steps_direct: int):
    sim = lambda status, steps: SimpleNamespace(status=status, steps=steps, converged=status == "converged",  # noqa: E731
                                                monotonic=status == "converged")
    rep = lambda status, steps, c: SimpleNamespace(sim=sim(status, steps), min_clearance=c)  # noqa: E731
    sched = SimpleNamespace(gains=np.array([0.9]), max_certified_G_norm=0.8, segments=[], certified=True)
    return SimpleNamespace(
        name="q", planned={"cost": 0.2, "length": 0.1, "max_G_norm": 0.5}, direct={"cost": 0.2, "length": 0.1},
        schedule=sched, direct_schedule=sched, direct_gain=0.9,
        sim_planned=rep("converged", 20, 0.013), sim_direct=rep(status_direct, steps_direct, 0.0361),
        corner_planned=[rep("converged", 20, 0.012)] * 2,
        corner_direct=[rep(status_direct, steps_direct, 0.0216), rep("converged", 30, 0.03)], uncovered=[], truth_name=None)


def test_the_clearance_of_a_run_that_stopped_says_so():
    from errplan.pipeline import summary_table

    text = summary_table([_run("left_workspace", 1)])
    line = next(x for x in text.splitlines() if "min clearance" in x)
    direct = line.split("direct", 1)[1]
    assert "36.1 mm over the 1 step it ran: LEFT THE WORKSPACE" in direct, line
    assert "1 of 2 corners left the workspace" in direct, line
    assert "planned 13.0 mm (corners >= 12.0 mm)" in line  # a converged run: as before
    ok = summary_table([_run("converged", 25)])
    assert "WORKSPACE" not in ok and "corners left" not in ok


# ----------------------------------------------------------------------------- the compile notice
def test_the_compile_notice_says_what_it_compiles_and_does_not_promise_once(tmp_path):
    """A fresh cache (a subprocess with its own NUMBA_CACHE_DIR, killed after the first line): the notice
    names the command and the kernels it starts with, and says that each kernel is compiled by the first
    command that needs it, not that everything happens once, on the first run (a later command that
    needs other kernels compiles them, and its notice is then true as well)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"), ERRPLAN_COMPILE_NOTICE="1",
               ERRPLAN_WARMUP="0")
    p = subprocess.Popen([sys.executable, "-m", "errplan", "fields", str(PORT), "--out", str(tmp_path / "f.npz"),
                          "--resolution", "0.02", "--rho-star"], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                         text=True, env=env, cwd=tmp_path)
    try:
        line = p.stderr.readline()
    finally:
        p.kill()
        p.wait()
    assert line.startswith("errplan fields: compiling numerical kernels"), line
    assert "starting with the planar arm's kinematics" in line or "starting with the worst-case fields" in line, line
    assert "first command that needs it" in line and "happens once, on the first run" not in line, line
    assert "docs/benchmarks.md#first-run" in line  # where the times are measured (the link test checks it)
    assert re.search(r"^## First run$", (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8"), re.M)


def test_the_notice_names_the_area_of_the_kernel():
    from errplan import jit
    from errplan.fields.kernels import worst_case_tile
    from errplan.planning import cellwalk

    assert jit.area_of(worst_case_tile.__module__) == "the worst-case fields"
    assert jit.area_of(cellwalk.__name__) == "the planner's cell walks"
    assert "(walk3)" in jit.notice(SimpleNamespace(__name__="walk3__native", __module__=cellwalk.__name__))


# ----------------------------------------------------------------------------- the pages as committed
def _hooks():
    import importlib.util

    spec = importlib.util.spec_from_file_location("errplan_docs_hooks", ROOT / "docs" / "_hooks" / "errplan_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_committed_scenario_reference_is_current():
    """``docs/reference/scenario.md`` is a committed page (it reads on disk and on the forge), generated by
    ``python docs/_hooks/errplan_docs.py`` from the parser's key tables: stale, this fails."""
    hooks = _hooks()
    committed = (ROOT / hooks.REFERENCE).read_text(encoding="utf-8")
    assert committed == hooks.scenario_reference(), "regenerate: python docs/_hooks/errplan_docs.py"
    assert "`length`" in committed and "## `[instrument]`" in committed or "[instrument]" in committed


def test_a_stale_scenario_reference_is_caught(tmp_path):
    hooks = _hooks()
    (tmp_path / "docs" / "reference").mkdir(parents=True)
    (tmp_path / hooks.REFERENCE).write_text(hooks.scenario_reference(), encoding="utf-8")
    assert hooks.reference_is_current(tmp_path)
    page = hooks.scenario_reference().replace("| `length` |", "| `shaft_length` |", 1)  # an old key's name
    (tmp_path / hooks.REFERENCE).write_text(page, encoding="utf-8")
    assert not hooks.reference_is_current(tmp_path)


_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$", re.M)


def _anchors(md: str) -> set[str]:
    """The anchors of a page's headings as the site makes them (Python-Markdown's toc slugs, duplicates
    numbered), and explicit ``{ #id }`` and ``<a id=...>`` ones."""
    from markdown.extensions.toc import slugify

    text = _FENCE.sub("", md)
    out, seen = set(), {}
    for _, title in _HEADING.findall(text):
        m = re.search(r"\{\s*#([\w-]+)[^}]*\}\s*$", title)
        if m:
            out.add(m.group(1))
            title = title[:m.start()]
        plain = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", title)
        plain = re.sub(r"<[^>]+>", "", plain).replace("`", "").replace("*", "").replace("\\", "")
        slug = slugify(plain, "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}_{n}")
    out.update(re.findall(r"<a\s+(?:name|id)=\"([^\"]+)\"", text))
    return out


def _api_anchor(page: Path, anchor: str) -> bool:
    """An anchor of a page mkdocstrings fills (``::: module`` lines): the dotted name of an object of a
    module the page documents, which must exist in the code as committed."""
    import importlib

    def resolve(dotted: str):
        parts = dotted.split(".")
        for k in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:k]))
            except ImportError:
                continue
            for part in parts[k:]:
                if not hasattr(obj, part):
                    return None
                obj = getattr(obj, part)
            return obj
        return None

    names = re.findall(r"^:::\s*([\w.]+)\s*$", page.read_text(encoding="utf-8"), re.M)
    return any((anchor == n or anchor.startswith(n + ".")) and resolve(anchor) is not None for n in names)


def broken_links(root: Path, docs: str = "docs") -> list[str]:
    """Every relative link (and image) of README.md and ``docs``/**/*.md that does not resolve in the tree
    under ``root``: a missing file, or an #anchor no heading of the target page makes."""
    pages = [root / "README.md"] + sorted((root / docs).rglob("*.md"))
    bad, anchors = [], {}
    for page in pages:
        text = _FENCE.sub("", page.read_text(encoding="utf-8"))
        text = re.sub(r"`[^`\n]*`", "", text)  # code spans are not links
        for target in _LINK.findall(text):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("/"):
                continue  # http(s), mailto: not the repository's
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(root)}: {target}"
            if not dest.exists():
                bad.append(where + " (no such file)")
                continue
            if anchor and dest.suffix == ".md":
                if dest not in anchors:
                    anchors[dest] = _anchors(dest.read_text(encoding="utf-8"))
                if anchor not in anchors[dest] and not _api_anchor(dest, anchor):
                    bad.append(where + " (no such anchor)")
    return bad


def test_every_relative_link_resolves_in_the_repository():
    assert broken_links(ROOT) == []


def test_the_link_check_catches_a_missing_page_and_anchor(tmp_path):
    (tmp_path / "pages").mkdir()
    (tmp_path / "pages" / "a.md").write_text("# Title\n\n## First run\n\n[ok](#first-run) [also](../README.md)\n",
                                             encoding="utf-8")
    (tmp_path / "README.md").write_text("[a](pages/a.md#first-run) [b](pages/b.md) [c](pages/a.md#nope)\n"
                                        "```\n[in code](pages/none.md)\n```\n", encoding="utf-8")
    assert broken_links(tmp_path, "pages") == ["README.md: pages/b.md (no such file)",
                                               "README.md: pages/a.md#nope (no such anchor)"]


# ----------------------------------------------------------------------------- labels that can be read
def test_close_ports_get_one_label_and_distant_ones_two():
    from errplan.recording.style import port_labels

    assert port_labels([0.0, 0.16], [0.0, 0.16], 0.4) == (["true port = estimated port"], None)
    t, e = port_labels([0.0, 0.16], [0.02, 0.17], 0.44)  # P1's Fig. 5 ports, 22 mm apart on a 44 cm field
    assert e is None and t == ["true port (white), estimated port (yellow) 22.4 mm away"]
    assert port_labels([0.0, 0.0, 0.16], [0.0, 0.1, 0.16], 0.3) == (["true port"], ["estimated port"])


def test_a_recording_labels_close_ports_once(tmp_path):
    """The planar recording as the demo writes it: P1's ports 22 mm apart carry one label between them."""
    rr = pytest.importorskip("rerun")
    from errplan.recording import plane

    logged = {}

    class Rec:
        def log(self, path, *items, **kw):
            logged.setdefault(path, []).extend(items)

    sc = errplan.load_scenario(PORT)
    mf = errplan.compute_fields(sc, 0.02, metrics=["G_norm"])
    plane._log_plan(Rec(), rr, sc, mf, [], [])
    t, e = logged["plane/port/true"][0], logged["plane/port/estimate"][0]
    assert t.labels is not None and "estimated port" in str(t.labels.as_arrow_array())
    assert e.labels is None


# ----------------------------------------------------------------------------- the docs' instructions, run
def _block_after(md: Path, marker: str) -> str:
    """The first fenced block after ``marker`` in ``md``."""
    text = md.read_text(encoding="utf-8")
    i = text.index(marker)
    m = re.search(r"^```[^\n]*\n(.*?)^```", text[i:], re.S | re.M)
    return m.group(1)


def _run_shell(commands: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    """Run the commands in bash, in a folder of their own that sees the repository's ``scenarios/``, with
    ``errplan`` the program of this checkout."""
    (tmp_path / "scenarios").symlink_to(ROOT / "scenarios")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "errplan"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m errplan "$@"\n', encoding="utf-8")
    shim.chmod(0o755)
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}", PYTHONPATH=str(ROOT),
               ERRPLAN_COMPILE_NOTICE="0", ERRPLAN_WARMUP="0")
    script = "set -e\n" + "\n".join(commands) + "\n"
    return subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=1200)


def _dollar_commands(block: str) -> tuple[list[str], list[str]]:
    """(commands, output lines) of a block of ``$ command`` lines (a trailing backslash continues one)."""
    cmds, out, cont = [], [], False
    for line in block.splitlines():
        if cont:
            cmds[-1] += "\n" + line
        elif line.startswith("$ "):
            cmds.append(line[2:])
        elif line.strip() and line.strip() != "...":
            out.append(line)
        cont = (cont or line.startswith("$ ")) and line.endswith("\\")
    return cmds, out


def test_the_dollar_commands_are_parsed():
    cmds, out = _dollar_commands("$ a \\\n  b\n$ c\nresult 1\n...\n")
    assert cmds == ["a \\\n  b", "c"] and out == ["result 1"]


@pytest.mark.slow
def test_the_readme_closing_the_loop_runs_as_written(tmp_path):
    """README's closing-the-loop example from a clean folder: its commands make the files they use, and
    print the lines it shows."""
    cmds, shown = _dollar_commands(_block_after(ROOT / "README.md", "**Closing the loop**"))
    assert any("> declared.toml" in c for c in cmds) and any("bench_friction.toml" in c for c in cmds)
    p = _run_shell(cmds, tmp_path)
    assert p.returncode == 0, p.stderr
    for line in shown:
        assert line.split() == [] or " ".join(line.split()) in " ".join(p.stdout.split()), line
    assert (tmp_path / "corrected.toml").is_file()


@pytest.mark.slow
def test_getting_started_runs_as_written(tmp_path):
    """Getting started's own scenario: copy a bundled one, then the commands as written (the viewer
    aside); the file it copies has the [uncertainty] table it tells the reader to edit."""
    block = _block_after(ROOT / "docs" / "getting-started.md", "## A scenario of your own")
    lines = [x for x in block.splitlines() if x.strip() and not x.lstrip().startswith("#")]
    cmds = [x for x in lines if not x.startswith("errplan view")]
    assert len(cmds) == len(lines) - 1 and cmds[0].startswith("cp scenarios/")
    for table in re.findall(r"\[([a-z_]+)\]", block.split("\n# edit", 1)[1].splitlines()[0]):
        assert f"[{table}]" in (ROOT / cmds[0].split()[1]).read_text(encoding="utf-8"), table
    p = _run_shell(cmds, tmp_path)
    assert p.returncode == 0, p.stderr
    assert {"mine.toml", "mine.npz", "mine.json", "mine.rrd"} <= set(os.listdir(tmp_path))


# ----------------------------------------------------------------------------- the demo's times
def test_the_demo_reports_cpu_that_adds_up_and_no_overlapping_wall(monkeypatch):
    """Two scenarios side by side, their steps overlapping in wall time (each 0-10 s): each block's CPU is
    its own steps' (main process and workers), the blocks add up to every step's CPU, and a block run
    side by side shows no wall time of its own."""
    from errplan.cli import demo as d

    steps = [{"scenario": "a", "step": "fields", "process": "worker", "start": 0, "end": 10, "cpu": 3.0},
             {"scenario": "b", "step": "fields", "process": "worker", "start": 0, "end": 10, "cpu": 5.0},
             {"scenario": "a", "step": "plan", "process": "main", "start": 0, "end": 10, "cpu": 1.0},
             {"scenario": "a", "step": "query 0", "process": "worker", "start": 0, "end": 10, "cpu": 2.0},
             {"scenario": "a", "step": "query 1", "process": "worker", "start": 0, "end": 10, "cpu": 2.5},
             {"scenario": "b", "step": "record", "process": "main", "start": 0, "end": 10, "cpu": 0.5}]
    monkeypatch.setattr(d, "_STEPS", steps)
    a, b = d.cpu_by_step(["a"]), d.cpu_by_step(["b"])
    assert a == {"fields": 3.0, "planning": 1.0, "gains + simulation": 4.5, "total": 8.5}
    assert b == {"fields": 5.0, "recording": 0.5, "total": 5.5}
    assert a["total"] + b["total"] == sum(e["cpu"] for e in steps)
    line = d._cpu_line(a)
    assert line == "time: CPU fields 3.0 s, planning 1.0 s, gains + simulation 4.5 s; 8.5 s in all"
    times = {"fields": 10.0, "plan": 10.0, "gains_simulation_record": 10.0, "total": 10.0, "side_by_side": True,
             "cpu": a}
    res = {"runs": [], "queries": []}
    text, doc = d._report(SimpleNamespace(name="a", dim=2), Path("a.toml"), None, res, False, times)
    assert "time: wall" not in text and line in text and doc["timing_s"]["cpu"] == a
    text, _ = d._report(SimpleNamespace(name="a", dim=2), Path("a.toml"), None, res, False, dict(times, side_by_side=False))
    assert "time: wall fields 10.0 s" in text and line in text  # one after another: the wall times too
