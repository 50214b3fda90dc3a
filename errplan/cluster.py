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


def _forked_task(conn, fn: Callable, args: tuple) -> None:
    """The body of a :class:`ForkedTasks` child: its own process group (so that pausing it pauses its own
    worker processes too), ``fn(*args)`` sent back as ``("ok", result)`` or ``("err", exception, traceback)``."""
    import traceback

    try:
        os.setpgid(0, 0)
    except OSError:  # pragma: no cover - not permitted here: pausing then reaches this process only
        pass
    try:
        res = fn(*args)
        t = os.times()
        out = ("ok", res, t.user + t.system + t.children_user + t.children_system)
    except BaseException as e:  # noqa: BLE001 - everything goes back to the parent
        out = ("err", e, traceback.format_exc())
    try:
        conn.send(out)
    except Exception:  # an unpicklable result or exception
        conn.send(("err", RuntimeError(repr(out[1])[:2000]), out[2] if len(out) > 2 else ""))
    conn.close()


class ForkedTasks:
    """Tasks started one by one in forked child processes, at most ``slots`` at a time, each with what
    this process holds when it starts (models, compiled kernels: nothing is pickled but the result).

    :meth:`start` forks a task now; :meth:`collect` waits for finished ones and returns ``(key, result)``
    pairs (and notes each one's times in :attr:`log`) (a task's exception is raised here, after every other child is ended); :meth:`limited` pauses
    (SIGSTOP, each child with its process group) all but ``n`` running tasks meanwhile: for a step of this
    process that must not share the cores (a planner with a time budget). The caller decides what to start
    and when; :meth:`close` ends whatever still runs.
    """

    def __init__(self, slots: int):
        self.slots = max(1, int(slots))
        self._ctx = mp.get_context("fork")
        self._running: dict = {}  # reader connection -> (key, process, started, light)
        self._paused: set = set()
        #: per finished task: key, start and end (perf_counter, s) and CPU seconds (its process and its workers)
        self.log: list[dict] = []

    @property
    def free(self) -> int:
        return self.slots - len(self._running)

    def __len__(self) -> int:
        return len(self._running)

    def start(self, key: Any, fn: Callable, *args, light: bool = False) -> None:
        """Run ``fn(*args)`` in a forked child. ``light``: a one-process task, the one :meth:`limited`
        keeps running first (a task that starts worker processes of its own is not light)."""
        import sys
        import time

        for f in (sys.stdout, sys.stderr):  # a child flushes its copy of the streams' buffers when it exits
            try:
                f.flush()
            except Exception:  # pragma: no cover
                pass
        r, w = self._ctx.Pipe(duplex=False)
        p = self._ctx.Process(target=_forked_task, args=(w, fn, args), daemon=False)
        p.start()
        try:  # as the child does: whichever runs first, the group exists before anyone signals it
            os.setpgid(p.pid, p.pid)
        except OSError:
            pass
        w.close()
        self._running[r] = (key, p, time.perf_counter(), light)

    def collect(self, timeout: float | None = None) -> list:
        """The ``(key, result)`` of every task that finished within ``timeout`` seconds (None: wait for one)."""
        import time
        from multiprocessing.connection import wait

        if not self._running:
            return []
        done = []
        for r in wait(list(self._running), timeout):
            key, p, t_start, _ = self._running.pop(r)
            try:
                msg = r.recv()
            except EOFError:
                msg = ("err", RuntimeError(f"the worker process of {key!r} ended without a result"), "")
            r.close()
            p.join()
            self._paused.discard(p.pid)
            if msg[0] != "ok":
                self.close()
                raise msg[1]
            self.log.append({"key": key, "start": t_start, "end": time.perf_counter(), "cpu": msg[2]})
            done.append((key, msg[1]))
        return done

    def _signal(self, pid: int, sig) -> None:
        try:
            os.killpg(pid, sig)
        except OSError:
            try:
                os.kill(pid, sig)
            except OSError:
                pass

    def limited(self, n: int):
        """A context in which at most ``n`` light running tasks go on (the oldest first); the others, and
        every task with worker processes of its own, are paused and resumed after it."""
        import contextlib
        import signal

        @contextlib.contextmanager
        def ctx():
            stop = getattr(signal, "SIGSTOP", None)
            if stop is None:  # pragma: no cover - not POSIX
                yield
                return
            light = sorted((v for v in self._running.values() if v[3]), key=lambda v: v[2])
            paused = [v[1].pid for v in self._running.values() if not v[3]] + [v[1].pid for v in light[max(0, n):]]
            for pid in paused:
                self._signal(pid, stop)
                self._paused.add(pid)
            try:
                yield
            finally:
                for pid in paused:
                    if pid in self._paused:
                        self._signal(pid, signal.SIGCONT)
                        self._paused.discard(pid)

        return ctx()

    def close(self) -> None:
        """End every running task (and its process group)."""
        import signal

        for r, (_, p, _, _) in list(self._running.items()):
            if p.is_alive():
                self._signal(p.pid, signal.SIGCONT)
                self._signal(p.pid, signal.SIGTERM)
            p.join(5)
            if p.is_alive():
                p.kill()
                p.join()
            r.close()
        self._running.clear()
        self._paused.clear()
