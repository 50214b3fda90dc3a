"""Independent tasks on local worker processes or on a dask.distributed cluster.

The only module that imports dask. ``map_tasks(fn, shared, items)`` returns ``[fn(shared, item) for
item in items]`` in order, whatever runs them:

- ``workers <= 1`` and no scheduler: in this process;
- ``workers = N``: N local worker processes (forked, so compiled kernels and the ``shared`` data
  are inherited, nothing is pickled but the items and the results);
- ``scheduler = "tcp://host:port"``: an existing dask.distributed cluster; ``shared`` is
  scattered to every worker once, items are tasks.

``fn`` must be a module-level function and deterministic: the results are identical either way
(a test runs a real ``distributed.LocalCluster`` against a local run). ``progress(done, total)``
is called in this process as tasks finish.
"""
from __future__ import annotations

import multiprocessing as mp
import os
from typing import Any, Callable, Sequence

from .errors import ErrplanError

_SHARED: dict[int, tuple[Callable, Any]] = {}


def default_workers() -> int:
    """All cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _run_local(key: int, item: Any) -> Any:
    fn, shared = _SHARED[key]
    return fn(shared, item)


def _run_remote(fn: Callable, shared: Any, item: Any) -> Any:
    return fn(shared, item)


def map_tasks(fn: Callable[[Any, Any], Any], shared: Any, items: Sequence[Any], *, workers: int | None = None,
              scheduler: str | None = None, progress: Callable[[int, int], None] | None = None) -> list:
    """``[fn(shared, item) for item in items]``, run locally, in worker processes or on a cluster."""
    n = len(items)
    if scheduler:
        return _map_dask(fn, shared, items, scheduler, progress)
    workers = default_workers() if workers is None else int(workers)
    if workers < 1:
        raise ErrplanError(f"--workers = {workers}: expected a number of worker processes >= 1")
    if workers == 1 or n <= 1:
        out = []
        for i, it in enumerate(items):
            out.append(fn(shared, it))
            if progress:
                progress(i + 1, n)
        return out
    key = id(shared)
    _SHARED[key] = (fn, shared)
    try:
        ctx = mp.get_context("fork")
        out: list = [None] * n
        with ctx.Pool(min(workers, n)) as pool:
            jobs = pool.imap_unordered(_indexed, [(key, i, it) for i, it in enumerate(items)])
            for done, (i, res) in enumerate(jobs, 1):
                out[i] = res
                if progress:
                    progress(done, n)
        return out
    finally:
        _SHARED.pop(key, None)


def _indexed(args):
    key, i, item = args
    return i, _run_local(key, item)


def _map_dask(fn, shared, items, scheduler: str, progress) -> list:
    try:
        from distributed import Client, as_completed
    except ImportError as e:  # pragma: no cover - a dependency
        raise ErrplanError(f"--scheduler {scheduler}: dask.distributed is not installed ({e})") from None
    try:
        client = Client(scheduler, timeout="5s")
    except (OSError, TimeoutError, ValueError) as e:
        raise ErrplanError(f"--scheduler {scheduler}: cannot reach a dask scheduler there ({e})") from None
    try:
        shared_f = client.scatter(shared, broadcast=True, hash=False)
        futs = [client.submit(_run_remote, fn, shared_f, it, pure=False) for it in items]
        index = {f.key: i for i, f in enumerate(futs)}
        out: list = [None] * len(items)
        for done, (fut, res) in enumerate(as_completed(futs, with_results=True), 1):
            out[index[fut.key]] = res
            if progress:
                progress(done, len(items))
        return out
    finally:
        client.close()
