"""The one module of errplan that imports rerun (rerun-sdk 0.41): the SDK on first use, and the atomic writer
every view records through. The views get rerun's modules from here."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from ..errors import ErrplanError


def rerun():
    """The ``rerun`` module (imported on first use: ``import errplan`` never loads it)."""
    import rerun as rr

    return rr


def blueprint():
    """``rerun.blueprint``."""
    import rerun.blueprint as rrb

    return rrb


def urdf():
    """``rerun.urdf`` (the URDF loader)."""
    import rerun.urdf as ru

    return ru


def write(path: str | os.PathLike, app_id: str, recording_id: str, default_blueprint, log: Callable) -> None:
    """Write one ``.rrd``: ``log(rec, rr)`` fills a recording stream saved to ``path`` with
    ``default_blueprint``. Written to a temporary file and renamed: nothing half-written on error."""
    rr = rerun()
    path = Path(path)
    if not path.parent.exists():
        raise ErrplanError(f"--record {path}: directory {path.parent} does not exist")
    tmp = path.with_name(path.name + ".part")
    rec = rr.RecordingStream(app_id, recording_id=recording_id, send_properties=False)
    rec.save(tmp, default_blueprint=default_blueprint)
    try:
        log(rec, rr)
        rec.flush()
    finally:
        rec.disconnect()
    os.replace(tmp, path)
