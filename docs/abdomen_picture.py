"""Draw the bundled abdomen and its demo paths as a PNG (README's picture; needs Pillow).

    errplan demo --json demo.json && python docs/abdomen_picture.py demo.json docs/abdomen.png

(or the JSON of ``errplan demo --scenario scenarios/abdomen.toml --json demo.json``, the abdomen alone).

An oblique orthographic view, y up: the organs (flat-shaded triangles, painter's order), the vessel, the
body wall (its outline and a few meridians), the port, each query's planned path (green) and direct
straight line (red), and the shaft from the port to a few tips of each planned path. The labels are drawn
last, each on a pale box, so no line crosses them.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(js: str, out: str, size: int = 900) -> None:
    from errplan.api import load_scenario
    from errplan.fields.compute import anatomy_model

    sc = load_scenario(ROOT / "scenarios" / "abdomen.toml")
    m = anatomy_model(sc)
    doc = json.loads(Path(js).read_text())
    qs = (doc["anatomy"] if "anatomy" in doc else doc)["queries"]
    # view: rotate about y by 35 deg, then tilt by 25 deg about x; project onto the screen x, y
    a, b = np.radians(35), np.radians(-25)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    R = Rx @ Ry
    centre = np.array([0.0, 0.0, 0.36])
    scale = size / 0.42

    def proj(p):
        q = (np.asarray(p, float) - centre) @ R.T
        return np.stack([size / 2 + scale * q[..., 0], size / 2 - scale * q[..., 1], q[..., 2]], -1)

    img = Image.new("RGB", (size, size), (250, 250, 248))
    d = ImageDraw.Draw(img, "RGBA")
    wv, wf = m.wall_mesh()
    W = proj(wv)
    light = np.array([0.3, 0.6, -0.75])
    light /= np.linalg.norm(light)
    # wall: back faces faint, as a shell
    tris = []
    for s in m.surfaces:
        P = proj(s.vertices)
        col = (90, 110, 200) if s.shape == "capsule" else (200, 95, 105)
        for f in s.faces:
            v = s.vertices[f] @ R.T
            n = np.cross(v[1] - v[0], v[2] - v[0])
            nn = np.linalg.norm(n)
            if nn == 0:
                continue
            shade = 0.45 + 0.55 * abs(float(n @ light) / nn)
            tris.append((P[f][:, 2].mean(), [tuple(P[i][:2]) for i in f], tuple(int(c * shade) for c in col)))
    for f in wf:
        z = W[f][:, 2].mean()
        if z > 0:  # the far half of the wall, behind everything
            d.polygon([tuple(W[i][:2]) for i in f], fill=(235, 215, 190, 60))
    for _, poly, col in sorted(tris, key=lambda t: -t[0]):
        d.polygon(poly, fill=col)
    port = proj(sc.port.estimate)
    labels = []  # (xy, text), drawn last
    for q in qs:
        pp = np.asarray(q["planned"]["path"])
        dp = np.asarray(q["direct"]["path"])
        for t in np.linspace(0, 1, 6):
            k = int(round(t * (len(pp) - 1)))
            tip = proj(pp[k])
            d.line([tuple(port[:2]), tuple(tip[:2])], fill=(120, 120, 120, 90), width=1)
        d.line([tuple(x) for x in proj(dp)[:, :2]], fill=(220, 40, 40), width=3)
        d.line([tuple(x) for x in proj(pp)[:, :2]], fill=(30, 160, 60), width=4)
        s = proj(pp[0])
        labels.append(((s[0] + 6, s[1] - 18), q["name"]))
    for f in wf:
        if W[f][:, 2].mean() <= 0:  # the near half, translucent on top
            d.polygon([tuple(W[i][:2]) for i in f], fill=(235, 205, 170, 18))
    d.ellipse([port[0] - 6, port[1] - 6, port[0] + 6, port[1] + 6], fill=(240, 200, 0), outline=(0, 0, 0))
    labels.append(((port[0] + 10, port[1] + 2), "port (on the wall)"))
    try:
        font = ImageFont.truetype("DejaVuSans.ttf", 13)
    except OSError:  # no DejaVu: Pillow's own font
        font = ImageFont.load_default()
    for xy, text in labels:
        x0, y0, x1, y1 = d.textbbox(xy, text, font=font)
        d.rectangle([x0 - 3, y0 - 2, x1 + 3, y1 + 2], fill=(255, 255, 252, 225), outline=(150, 150, 150))
        d.text(xy, text, fill=(20, 20, 20), font=font)
    d.text((12, 12), "errplan: the bundled abdomen (scenarios/abdomen.toml)", fill=(20, 20, 20), font=font)
    d.text((12, 30), "organs (red meshes), vessel (blue capsule), body wall (beige); planned paths green, "
                     "straight lines red; grey: shafts from the port", fill=(60, 60, 60), font=font)
    img.save(out)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
