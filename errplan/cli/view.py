"""``errplan view F.rrd``: open a recording in the rerun viewer (native; ``rerun F.rrd``)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from ..errors import ErrplanError


def viewer_command(path: str | os.PathLike) -> list[str]:
    """The command that opens ``path``: the ``rerun`` CLI on PATH, else the one bundled with rerun-sdk."""
    exe = shutil.which("rerun")
    if exe:
        return [exe, str(path)]
    return [sys.executable, "-m", "rerun_cli", str(path)]


def viewer_env() -> dict:
    """The environment for a rerun subprocess: ``CI=1`` keeps the rerun CLI from sending analytics."""
    env = dict(os.environ)
    env["CI"] = "1"
    return env


def check_recording(path: str | os.PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise ErrplanError(f"{p}: recording not found (write one with `errplan plan SCENARIO --record {p.name}` "
                           f"or `errplan demo`)")
    if p.is_dir():
        raise ErrplanError(f"{p}: is a directory, expected an .rrd recording")
    with open(p, "rb") as f:
        head = f.read(4)
    if head[:3] != b"RRF":
        raise ErrplanError(f"{p}: not a rerun recording (the file does not start with an .rrd header)")
    return p


def run(args) -> int:
    p = check_recording(args.recording)
    cmd = viewer_command(p)
    try:
        return subprocess.call(cmd, env=viewer_env())
    except FileNotFoundError:
        raise ErrplanError("the rerun viewer was not found: install rerun-sdk (pip install 'rerun-sdk>=0.41,<0.42')") from None
