"""Recordings of a setup with several arms: `errplan plan SETUP --record` and `errplan tolerance SETUP
--record` (triad placement) read back with rerun.chunk.RrdReader; the view cone and the camera at the lens
checked against plain vector algebra."""
from __future__ import annotations

import json
import math
from collections import Counter

import numpy as np
import pytest

from conftest import to_toml
from errplan.cli import main
from errplan.recording.setup import camera_rotation, view_cone_mesh
from test_setup import triad_doc

rrc = pytest.importorskip("rerun.chunk")


def _angle(u, v) -> float:  # plain vector algebra
    u, v = np.asarray(u, float), np.asarray(v, float)
    return math.acos(max(-1.0, min(1.0, float(u @ v) / (np.linalg.norm(u) * np.linalg.norm(v)))))


def _lens(port, look_at, insertion):  # plain vector algebra
    u = np.asarray(look_at, float) - np.asarray(port, float)
    return np.asarray(port, float) + insertion * u / np.linalg.norm(u)


def _read(path):
    """{entity: rows}, {entity: {column: [values of every row]}}."""
    rows, cols = Counter(), {}
    for ch in rrc.RrdReader(path).stream().to_chunks():
        rows[ch.entity_path] += ch.num_rows
        b = ch.to_record_batch()
        d = cols.setdefault(ch.entity_path, {})
        for name in (n for n in b.schema.names if ":" in n):  # the components (not the time columns)
            d.setdefault(name.split(":")[-1], []).extend(b.column(name).to_pylist())
    return rows, cols


def _last(cols, entity, key):
    vals = [v for v in cols[entity][key] if v is not None]
    return np.asarray(vals[-1], float)


def test_view_cone_and_camera_by_vector_algebra():
    rng = np.random.default_rng(3)
    for _ in range(5):
        lens = rng.normal(size=3)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        fov, far = rng.uniform(0.2, 2.5), rng.uniform(0.05, 0.3)
        V, T = view_cone_mesh(lens, axis, fov, far, n=16)
        assert np.allclose(V[0], lens) and V.shape == (18, 3) and T.shape == (32, 3)
        for v in V[1:-1]:  # the rim: at the half angle from the axis, at depth far
            assert abs(_angle(v - lens, axis) - fov / 2) < 1e-9
            assert abs((v - lens) @ axis - far) < 1e-12
        assert np.allclose(V[-1], lens + far * axis)
        assert T.max() == len(V) - 1 and T.min() == 0
        R = camera_rotation(axis)
        assert np.allclose(R.T @ R, np.eye(3)) and abs(np.linalg.det(R) - 1) < 1e-12
        assert np.allclose(R[:, 2], axis)  # forward (z of RDF) along the optical axis
        up = np.array([0.0, 1.0, 0.0])
        assert R[:, 1] @ up <= 1e-12 and abs(R[:, 0] @ up) < 1e-12  # image down is world down-ish, right level
    R = camera_rotation([0.0, 1.0, 0.0])  # looking straight up: still a rotation
    assert np.allclose(R.T @ R, np.eye(3)) and np.allclose(R[:, 2], [0, 1, 0])


def _setup_file(tmp_path, **tol):
    doc = triad_doc()
    doc["fields"]["resolution"] = 0.02  # small fields: the recording is tested, not the plan
    doc["tolerance"][0].update(tol)
    src = tmp_path / "s.toml"
    src.write_text(to_toml(doc), encoding="utf-8")
    return src, doc


def test_plan_record_of_a_setup(tmp_path, capsys):
    src, doc = _setup_file(tmp_path)
    rrd, js = tmp_path / "p.rrd", tmp_path / "p.json"
    assert main(["-q", "plan", str(src), "--record", str(rrd), "--json", str(js), "--iterations", "750"]) == 0
    assert "recording:" in capsys.readouterr().out
    rows, cols = _read(rrd)
    plan = json.loads(js.read_text())
    arms = {a["name"]: a for a in doc["arm"]}
    e = doc["endoscope"]
    lens = _lens(e["port"]["estimate"], e["look_at"], e["insertion"])
    # the endoscope: cone apex and camera at the lens, camera looking along the optical axis
    cone = np.asarray(cols["/world/endoscope/cone"]["vertex_positions"][0], float)
    assert np.allclose(cone[0], lens, atol=1e-6)
    assert np.allclose(_last(cols, "/world/endoscope/lens", "positions")[0], lens, atol=1e-6)
    assert np.allclose(_last(cols, "/world/endoscope/camera", "translation"), lens, atol=1e-6)
    assert "/world/endoscope/shaft" in rows
    assert rrc.RrdReader(rrd).blueprints()
    states = {}
    for q in plan["queries"]:
        n = q["arm"]
        qe = f"/world/queries/{n}_{q['name'].replace(' ', '_')}"
        assert np.allclose(cols[qe + "/planned"]["strips"][0], q["planned"]["path"], atol=1e-6)
        assert np.allclose(cols[qe + "/direct"]["strips"][0], q["direct"]["path"], atol=1e-6)
        states[n] = states.get(n, 0) + 1
    for n, a in arms.items():
        base = f"/world/arms/{n}"
        links = [k for k in rows if k.startswith(base + "/links/")]
        assert len(links) == 5  # the PHANToM's five visual objects
        # its own motion, plus one rest pose while every other arm's query plays
        others = sum(v for m, v in states.items() if m != n)
        assert rows[base + "/chain"] > others >= 1 and all(rows[k] == rows[base + "/chain"] for k in links)
        port = np.asarray(a["port"]["position"], float)
        assert np.allclose(_last(cols, base + "/port", "positions")[0], port, atol=1e-6)
        L = a["instrument"]["length"]
        for strip in cols[base + "/shaft"]["strips"]:  # wrist, port, tip: a straight shaft of length L
            w, p, t = np.asarray(strip[0], float)
            assert np.allclose(p, port, atol=1e-6)
            assert abs(np.linalg.norm(t - w) - L) < 1e-5
            assert abs(np.linalg.norm(t - p) + np.linalg.norm(p - w) - L) < 1e-5
    for o in ("stomach", "liver", "kidney", "vessel", "body_wall"):
        assert rows[f"/world/anatomy/{o}"] == 1


def test_triad_record(tmp_path, capsys):
    src, doc = _setup_file(tmp_path, spacing=0.06, resolution=0.04)
    rrd, js = tmp_path / "t.rrd", tmp_path / "t.json"
    assert main(["-q", "tolerance", str(src), "--record", str(rrd), "--json", str(js), "--workers", "1"]) == 0
    capsys.readouterr()
    d = json.loads(js.read_text())["tolerances"][0]
    rows, cols = _read(rrd)
    base = "/world/triad/triad_for_the_task_region"
    e = doc["endoscope"]
    for role in ("left", "right", "endoscope"):
        assert np.allclose(cols[f"{base}/chosen/{role}"]["positions"][0], [d["best"]["ports"][role]], atol=1e-6)
        assert np.allclose(cols[f"{base}/candidates/{role}"]["positions"][0], d["candidates"][role], atol=1e-6)
    lens = _lens(d["best"]["ports"]["endoscope"], e["look_at"], e["insertion"])
    assert np.allclose(cols[f"{base}/endoscope/cone"]["vertex_positions"][0][0], lens, atol=1e-6)
    X = np.asarray(cols[f"{base}/targets"]["positions"][0], float)
    assert len(X) == d["targets"]
    p1, p2 = (np.asarray(d["best"]["ports"][r]) for r in ("left", "right"))
    m = np.degrees([_angle(x - p1, x - p2) for x in X])
    got = [v[0] if isinstance(v, list) else v for v in cols[f"{base}/manipulation_angle"]["scalars"] if v is not None]
    assert np.allclose(got, m, atol=1e-4)
    ma = d["best"]["manipulation_angle"]
    assert abs(math.radians(m.mean()) - ma["mean"]) < 1e-5 and abs(math.radians(m.min()) - ma["min"]) < 1e-5
    for role in ("left", "right"):  # one shaft from the chosen port to every target
        strips = np.asarray(cols[f"{base}/shafts/{role}"]["strips"][0], float)
        assert strips.shape == (len(X), 2, 3)
        assert np.allclose(strips[:, 0], d["best"]["ports"][role], atol=1e-6) and np.allclose(strips[:, 1], X, atol=1e-6)


def test_plan_record_of_one_arm_of_a_setup(tmp_path, capsys):
    """--arm: that arm moves along its plan; the other is drawn once, at its rest (tip at `rest`)."""
    src, doc = _setup_file(tmp_path)
    rrd = tmp_path / "p.rrd"
    assert main(["-q", "plan", str(src), "--arm", "right", "--record", str(rrd), "--iterations", "750"]) == 0
    capsys.readouterr()
    rows, cols = _read(rrd)
    assert rows["/world/arms/left/chain"] == 1 and rows["/world/arms/right/chain"] > 1
    assert "/world/queries/right_right_reach/planned" in rows and not any("left_reach" in k for k in rows)
    rest = doc["arm"][0]["rest"]
    assert np.allclose(_last(cols, "/world/arms/left/tip", "positions")[0], rest, atol=1e-6)
    assert np.allclose(cols["/world/arms/left/shaft"]["strips"][0][0][2], rest, atol=1e-6)
