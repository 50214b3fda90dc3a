"""Robot-description packages: where ``package://NAME/PATH`` URIs resolve (docs/interfaces.md, "Spatial
scenarios").

A package URI names a file inside a ROS-style description package. errplan looks for the package, in this
order, in

1. the scenario's ``package_path`` (each entry is a folder holding packages, or the package itself);
2. ``$ROS_PACKAGE_PATH`` (the same);
3. the description packages installed in this Python environment: every ``share`` folder of the
   environment's prefixes (``sys.prefix``, the site-packages folders and their ``cmeel.prefix``, where
   pip packages such as example-robot-data install), each ``share/NAME`` a package and each
   ``share/*/robots/NAME`` too (example-robot-data's layout: ``share/example-robot-data/robots/ur_description``).

So a scenario names no path of a machine, and works wherever the package is installed. The lowest layer:
standard library only.
"""
from __future__ import annotations

import os
import site
import sys
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Sequence

SCHEME = "package://"


def split_uri(uri: str) -> tuple[str, str] | None:
    """``("NAME", "PATH")`` of ``package://NAME/PATH``, or None for any other string."""
    if not uri.startswith(SCHEME):
        return None
    name, _, rest = uri[len(SCHEME):].partition("/")
    return (name, rest) if name else None


@lru_cache(maxsize=1)
def installed_roots() -> tuple[Path, ...]:
    """Folders of this environment that hold description packages (existing ones, in a fixed order)."""
    prefixes: list[Path] = []
    for p in [sys.prefix, sys.base_prefix, *_site_dirs()]:
        prefixes += [Path(p), Path(p) / "cmeel.prefix"]
    roots: list[Path] = []
    for pre in prefixes:
        share = pre / "share"
        if not share.is_dir():
            continue
        roots.append(share)
        roots += sorted(r for r in share.glob("*/robots") if r.is_dir())
    seen, out = set(), []
    for r in roots:
        key = r.resolve()
        if key not in seen:
            seen.add(key)
            out.append(r)
    return tuple(out)


def _site_dirs() -> list[str]:
    try:
        dirs = list(site.getsitepackages())
    except AttributeError:  # pragma: no cover - some virtualenv tools drop it
        dirs = []
    user = getattr(site, "getusersitepackages", lambda: None)()
    return dirs + ([user] if user else [])


def search_dirs(package_path: Sequence[str | os.PathLike] = (), relative_to: str | os.PathLike | None = None,
                installed: bool = True) -> list[Path]:
    """Where packages are looked for, in order: ``package_path`` (relative entries against
    ``relative_to``), ``$ROS_PACKAGE_PATH``, then (``installed``) this environment's package roots."""
    dirs: list[Path] = []
    for d in list(package_path) + [d for d in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if d]:
        p = Path(d)
        if not p.is_absolute() and relative_to is not None:
            p = Path(relative_to) / p
        dirs.append(p)
    if installed:
        dirs += installed_roots()
    return dirs


def resolve(uri: str, dirs: Iterable[Path]) -> Path | None:
    """The file a ``package://`` URI names, looked up in ``dirs`` (as ``DIR/NAME/PATH``, or ``DIR/PATH``
    when DIR is the package itself), or None."""
    parts = split_uri(uri)
    if parts is None:
        return None
    name, rest = parts
    for base in dirs:
        for cand in (base / name / rest, base / rest if base.name == name else None):
            if cand is not None and cand.is_file():
                return cand.resolve()
    return None


def resolve_package_uri(uri: str, package_path: Sequence[str | os.PathLike] = (),
                        relative_to: str | os.PathLike | None = None) -> Path | None:
    """:func:`resolve` over :func:`search_dirs`."""
    return resolve(uri, search_dirs(package_path, relative_to))


def ros_package_path(package_path: Sequence[str | os.PathLike] = (), relative_to=None) -> str:
    """A ``ROS_PACKAGE_PATH`` value holding every search folder, for loaders that read that variable (rerun's
    URDF loader): the scenario's folders, the environment's, then the installed roots."""
    return os.pathsep.join(str(d) for d in search_dirs(package_path, relative_to))
