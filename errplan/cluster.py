"""Independent tasks on local worker processes or on a dask.distributed cluster.

The only module that imports dask. ``map_tasks(fn, shared, items)`` returns ``[fn(shared, item) for
item in items]`` in order, whatever runs them:

- ``workers <= 1`` and no scheduler: in this process;
- ``workers = N``: N local worker processes (forked, so compiled kernels and the ``shared`` data
  are inherited, nothing is pickled but the items and the results);
- ``scheduler = "tcp://host:port"``: an existing dask.distributed cluster; ``shared`` is
  scattered once (the workers copy it from each other), items are tasks. A worker lost at any moment changes nothing but
  time: the data is scattered again when no worker holds it, lost tasks run again (``_map_dask``).

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


#: Seconds a ``--scheduler`` run waits for a worker when the cluster has none (at the start, or after every
#: worker it had was lost) before it stops with an error naming the scheduler.
WORKER_WAIT = 60.0
#: Times one task may be lost with its worker (each time after the scheduler's own retries) before the run
#: stops: a task that ends every worker it runs on is an error, not bad luck.
MAX_LOSSES = 3
#: Attempts at scattering the shared data (a worker that dies while it receives it fails the attempt).
SCATTER_TRIES = 5
_POLL = 0.5  # seconds between looks at the cluster while tasks run


def _lost_kinds() -> tuple:
    """The exceptions by which dask reports a lost worker or lost data (never raised by a task itself); the
    second is the scheduler giving up on a task whose workers kept dying."""
    from asyncio import CancelledError as AsyncCancelled
    from concurrent.futures import CancelledError

    from distributed import KilledWorker
    from distributed.comm.core import CommClosedError

    # distributed's FutureCancelledError and FuturesCancelledError (a cancelled wait) are CancelledErrors
    return (CancelledError, KilledWorker, AsyncCancelled, CommClosedError, OSError, TimeoutError)


def _map_dask(fn, shared, items, scheduler: str, progress) -> list:
    """The tasks on a dask cluster. A worker may die at any moment: ``shared`` is scattered (the workers
    copy it from each other as their tasks need it) and scattered again from this process when no copy is
    left (scattered data cannot be recomputed by the scheduler); the tasks a lost worker ran are run again
    by the scheduler and, when it gives up (``KilledWorker``) or their data is gone
    (``FutureCancelledError``), resubmitted from here, at most ``MAX_LOSSES`` times each. The results are the tasks' results whoever ran them.
    No worker for ``WORKER_WAIT`` seconds is one :class:`ErrplanError` naming the scheduler."""
    try:
        from distributed import Client
        from distributed import wait as dwait
    except ImportError as e:  # pragma: no cover - a dependency
        raise ErrplanError(f"--scheduler {scheduler}: dask.distributed is not installed ({e})") from None
    try:
        client = Client(scheduler, timeout="5s")
    except (OSError, TimeoutError, ValueError) as e:
        raise ErrplanError(f"--scheduler {scheduler}: cannot reach a dask scheduler there ({e})") from None
    try:
        return _run_on(client, dwait, fn, shared, items, scheduler, progress)
    finally:
        client.close()


def _run_on(client, dwait, fn, shared, items, scheduler: str, progress) -> list:
    import time

    lost_kinds = _lost_kinds()
    killed = lost_kinds[1]  # the scheduler gave up on a task whose workers kept dying
    n = len(items)
    out: list = [None] * n
    losses = [0] * n
    done = 0

    def no_workers(what: str) -> ErrplanError:
        return ErrplanError(f"--scheduler {scheduler}: {what} (no worker for {WORKER_WAIT:g} s; {done} of {n} "
                            f"tasks done); start workers there (dask worker {scheduler}) and run again")

    def workers() -> int:
        try:
            return len(client.nthreads())
        except lost_kinds as e:
            raise ErrplanError(f"--scheduler {scheduler}: lost the scheduler ({e})") from None

    def await_workers(what: str) -> None:
        if workers():
            return
        try:
            client.wait_for_workers(1, timeout=WORKER_WAIT)
        except lost_kinds:
            raise no_workers(what) from None

    def scatter(first: bool):
        last = None
        for _ in range(SCATTER_TRIES):
            await_workers("no worker to send the data to" if first and last is None else "every worker was lost")
            try:
                # One object, one key (a dict or a list given as such would be scattered item by item), to
                # one worker: the others fetch it from their peers as their tasks need it. No broadcast: the
                # scheduler's replication retries a worker that died meanwhile without end.
                return client.scatter([shared], hash=False)[0]
            except lost_kinds as e:  # a worker died while it received the data: again, to the workers left
                last = e
                time.sleep(_POLL)
        raise ErrplanError(f"--scheduler {scheduler}: the data could not be sent to the workers in "
                           f"{SCATTER_TRIES} tries (workers lost while they received it: {last})")

    shared_f, sent = None, False
    todo = list(range(n))
    pending: dict = {}  # future -> item index
    alone_since = None
    while todo or pending:
        if todo:
            if shared_f is None or shared_f.status != "finished":  # no copy left (or never sent)
                shared_f, sent = scatter(not sent), True
            for i in todo:
                pending[client.submit(_run_remote, fn, shared_f, items[i], pure=False)] = i
            todo = []
        try:
            dwait(list(pending), timeout=_POLL, return_when="FIRST_COMPLETED")
        except lost_kinds:  # nothing finished within the poll (or a wait cut by a loss): look again below
            pass
        for fut in [f for f in pending if f.done()]:
            i = pending.pop(fut)
            if fut.status == "error":
                exc = fut.exception()
                if not isinstance(exc, killed):  # the task's own error: as a local run raises it
                    raise exc
            elif fut.status == "finished":
                try:
                    out[i] = fut.result()
                except lost_kinds:  # its worker died before the result came back
                    pass
                else:
                    done += 1
                    if progress:
                        progress(done, n)
                    continue
            losses[i] += 1
            if losses[i] > MAX_LOSSES:
                raise ErrplanError(f"--scheduler {scheduler}: task {i + 1} of {n} was lost with its worker "
                                   f"{losses[i]} times (each after the scheduler's own retries): a task that ends "
                                   f"its worker, or workers that keep dying")
            todo.append(i)
        if todo and shared_f is not None and shared_f.status != "finished":
            shared_f = None
        if (todo or pending) and not workers():
            alone_since = time.monotonic() if alone_since is None else alone_since
            if time.monotonic() - alone_since > WORKER_WAIT:
                raise no_workers("every worker was lost")
        else:
            alone_since = None
    return out


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
