"""``errplan view F.rrd [--web]``: open a recording in the rerun viewer (native ``rerun F.rrd``, or
the web viewer ``rerun --web-viewer F.rrd``). Every rerun subprocess runs with ``CI=1``: the rerun
CLI then sends no analytics."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from ..errors import ErrplanError


def viewer_command(path: str | os.PathLike, web: bool = False) -> list[str]:
    """The command that opens ``path``: the ``rerun`` CLI on PATH, else the one bundled with rerun-sdk
    (``--web-viewer``: serve the web viewer instead of opening the native one)."""
    exe = shutil.which("rerun")
    cmd = [exe] if exe else [sys.executable, "-m", "rerun_cli"]
    return cmd + (["--web-viewer"] if web else []) + [str(path)]


def has_display(env=None) -> bool:
    """False on Linux without an X11 or Wayland display (the native viewer cannot open a window)."""
    env = os.environ if env is None else env
    if not sys.platform.startswith("linux"):
        return True
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


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
    try:
        with open(p, "rb") as f:
            head = f.read(4)
    except OSError as e:
        raise ErrplanError(f"{p}: cannot read the recording: {e.strerror or e}") from None
    if head[:3] != b"RRF":
        raise ErrplanError(f"{p}: not a rerun recording (the file does not start with an .rrd header)")
    return p


def run(args) -> int:
    p = check_recording(args.recording)
    web = bool(getattr(args, "web", False))
    if not web and not has_display():
        raise ErrplanError(f"no display (DISPLAY and WAYLAND_DISPLAY are unset): serve the web viewer instead with "
                           f"`errplan view --web {p}` and open http://localhost:9090")
    cmd = viewer_command(p, web)
    if web:
        print(f"serving {p} in the rerun web viewer at http://localhost:9090 (Ctrl-C to stop)")
    try:
        return subprocess.call(cmd, env=viewer_env())
    except FileNotFoundError:
        raise ErrplanError("the rerun viewer was not found: install rerun-sdk (pip install 'rerun-sdk>=0.41,<0.42')") from None
