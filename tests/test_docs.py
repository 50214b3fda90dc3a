"""The documentation: the site builds with warnings as errors, every ``docs/...`` path cited anywhere
exists, the Python API's examples run, the scenario reference covers every key the bundled scenarios use,
and every command's ``--help`` explains every option with its default."""
from __future__ import annotations

import argparse
import ast
import doctest
import importlib.util
import os
import re
import subprocess
import sys
import time
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore

import pytest

import errplan
from errplan.cli import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[1]
HOOKS = ROOT / "docs" / "_hooks" / "errplan_docs.py"


def _hooks():
    spec = importlib.util.spec_from_file_location("errplan_docs_hooks", HOOKS)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# ------------------------------------------------------------------ the site
def test_site_builds_strict(tmp_path):
    """``mkdocs build --strict``: a broken link, a missing page or API object, an undocumented scenario key
    or any other warning fails the build (and this test)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), NO_MKDOCS_2_WARNING="1")
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                        "-d", str(tmp_path / "site")], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    elapsed = time.perf_counter() - t0
    log = r.stdout + r.stderr
    assert r.returncode == 0, log
    assert "WARNING" not in log, log
    assert elapsed < 120, elapsed
    site = tmp_path / "site"
    ref = (site / "reference" / "scenario" / "index.html").read_text(encoding="utf-8")
    assert "coupled_limits" in ref and "port_placement" in ref
    api = (site / "reference" / "api" / "index.html").read_text(encoding="utf-8")
    for name in errplan._API:
        assert f"errplan.api.{name}" in api or f"errplan.scenario.{name}" in api, name
    for cmd in COMMANDS:
        page = (site / "commands" / cmd / "index.html").read_text(encoding="utf-8")
        assert "<table>" in page, cmd  # the generated options table


# ------------------------------------------------------------------ cited paths
_CITED = re.compile(r"(?<![\w/.-])docs/[\w./-]*[\w]")
_SCANNED = ("errplan", "tests", "benchmarks", "docs")
_SUFFIXES = {".py", ".md", ".toml", ".sh", ".txt", ".yml"}


def cited_docs_paths(root: Path) -> dict[str, list[str]]:
    """``{cited path: [where, ...]}`` for every ``docs/...`` path written in the scanned folders and the
    README (a trailing ``.`` of a sentence is not part of the path)."""
    found: dict[str, list[str]] = {}
    files = [root / "README.md"] + [p for d in _SCANNED for p in sorted((root / d).rglob("*"))
                                    if p.is_file() and p.suffix in _SUFFIXES]
    for f in files:
        for i, line in enumerate(f.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            for m in _CITED.finditer(line):
                found.setdefault(m.group(0), []).append(f"{f.relative_to(root)}:{i}")
    return found


def test_cited_docs_paths_exist():
    cited = cited_docs_paths(ROOT)
    assert {"docs/physics.md", "docs/interfaces.md", "docs/design.md"} <= set(cited)
    missing = {p: where[:3] for p, where in cited.items() if not (ROOT / p).exists()}
    assert not missing, missing


def test_cited_docs_paths_catches_a_missing_page(tmp_path):
    d = "docs"  # (not written next to a slash here, so that this file cites no page itself)
    (tmp_path / d).mkdir()
    (tmp_path / "errplan").mkdir()
    (tmp_path / "README.md").write_text(f"see {d}/real.md and https://example.org/{d}/remote.md\n")
    (tmp_path / d / "real.md").write_text("x")
    (tmp_path / "errplan" / "m.py").write_text(f'"""({d}/gone.md, "Section"); {d}/real.md."""\n')
    cited = cited_docs_paths(tmp_path)
    assert set(cited) == {f"{d}/real.md", f"{d}/gone.md"}
    assert cited[f"{d}/gone.md"] == [str(Path("errplan/m.py")) + ":1"]


# ------------------------------------------------------------------ the Python API
def test_public_api_has_numpydoc_docstrings_with_examples_that_run(monkeypatch):
    """Every name ``import errplan`` exposes: a numpydoc docstring with Parameters (functions), Returns
    and Examples sections, and the examples pass (run from the repository's root, as documented)."""
    monkeypatch.chdir(ROOT)
    finder = doctest.DocTestFinder()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for name in errplan._API:
        obj = getattr(errplan, name)
        doc = obj.__doc__ or ""
        assert "Examples\n    --------" in doc, name
        if callable(obj) and not isinstance(obj, type):
            assert "Parameters\n    ----------" in doc and "Returns\n    -------" in doc, name
        tests = [t for t in finder.find(obj, name, globs={}) if t.examples and t.name == name]
        assert tests, name
        for t in tests:
            runner.run(t)
    assert runner.failures == 0, f"{runner.failures} example(s) failed (output above)"


# ------------------------------------------------------------------ the scenario reference
def test_every_check_keys_call_takes_its_keys_from_the_published_tables():
    """The scenario reference is generated from ``TABLE_KEYS`` & co.: a table checked against a literal
    tuple would be missing from it."""
    tree = ast.parse((ROOT / "errplan" / "scenario.py").read_text(encoding="utf-8"))
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "_check_keys"]
    assert len(calls) >= 15
    for c in calls:
        for node in ast.walk(c.args[2]):
            assert not isinstance(node, ast.Tuple) or not node.elts, ast.unparse(c)


def _keys_used(doc: dict) -> set[str]:
    out = set()
    for k, v in doc.items():
        out.add(k)
        if isinstance(v, dict):
            out |= _keys_used(v)
        elif isinstance(v, list):
            for x in v:
                if isinstance(x, dict):
                    out |= _keys_used(x)
    return out


def test_scenario_reference_lists_every_key_of_every_bundled_scenario():
    page = _hooks().scenario_reference()
    listed = set(re.findall(r"^\| `([\w]+)` \|", page, flags=re.M))
    listed |= {e for e in errplan.scenario.EFFECT_PARAMS} | set(re.findall(r"`(\w+)`", page))
    for f in sorted((ROOT / "scenarios").glob("*.toml")):
        used = _keys_used(tomllib.loads(f.read_text(encoding="utf-8"))) - {"x", "y", "z"}  # region axes
        assert used <= listed, (f.name, used - listed)


def test_scenario_reference_fails_on_an_undocumented_key(monkeypatch):
    hooks = _hooks()
    from errplan import scenario

    monkeypatch.setitem(scenario.TABLE_KEYS, "[fields]", scenario.TABLE_KEYS["[fields]"] + ("brand_new",))
    with pytest.raises(Exception, match="brand_new"):
        hooks.scenario_reference()


# ------------------------------------------------------------------ the command line
def _subparsers():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return parser, sub.choices


def test_every_option_of_every_command_has_help_with_its_default():
    parser, subs = _subparsers()
    assert set(subs) == set(COMMANDS)
    for prog, p in [("errplan", parser), *subs.items()]:
        for a in p._actions:
            if isinstance(a, (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)):
                continue
            text = (a.help or "") % {"default": a.default, "prog": p.prog}
            assert text.strip(), (prog, a.dest)
            if a.option_strings and not a.required:
                assert "default:" in text, (prog, a.option_strings, text)
                if a.default not in (None, False):
                    assert str(a.default) in text, (prog, a.option_strings, text)


def test_command_pages_list_every_option():
    hooks = _hooks()
    _, subs = _subparsers()
    for cmd, p in subs.items():
        table = hooks.options_table(cmd)
        for a in p._actions:
            for flag in a.option_strings:
                assert f"`{flag}" in table or f", {flag}" in table, (cmd, flag)
        page = (ROOT / "docs" / "commands" / f"{cmd}.md").read_text(encoding="utf-8")
        assert f"<!-- errplan-options: {cmd} -->" in page, cmd


def test_version():
    r = subprocess.run([sys.executable, "-m", "errplan", "--version"], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == f"errplan {errplan.__version__}", r


# ------------------------------------------------------------------ user documentation
_ISSUE = re.compile(r"issue [0-9]|[Ii]ssue #?[0-9]")
#: an abbreviated commit hash: 7 to 12 hex digits with at least one letter and one digit
_HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,12}\b")


def test_no_issue_numbers_or_commit_hashes_in_user_documentation_or_docstrings():
    files = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md")),
             *sorted((ROOT / "errplan").rglob("*.py"))]
    hits = [f"{f.relative_to(ROOT)}:{i}: {line.strip()[:80]}" for f in files
            for i, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1)
            if _ISSUE.search(line) or _HASH.search(line)]
    assert not hits, hits
    assert _HASH.search("the suite at f832455 took") and not _HASH.search("deadbeef"[:6] + " 1234567")


def test_readme_is_a_front_page_and_ci_runs_its_test_command():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 250
    m = re.search(r"## Run the tests\s+```bash\n(.+?)\n```", readme)
    assert m, "the README's test command"
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert m.group(1).strip() in [line.strip() for line in ci.splitlines()]
    assert "mkdocs serve" in readme
