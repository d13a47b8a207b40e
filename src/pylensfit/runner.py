"""Running tasks: in this process, on a local pool of worker processes, or on a
dask.distributed cluster.

The pipeline (:func:`pylensfit.measure`) and the validation harness hand their work to
:func:`run_tasks` as a list of tasks, each a picklable mapping or dataclass that the task
function takes as its only argument, and receive ``(task, result)`` pairs as the tasks
finish.

* ``jobs = 1`` (and no scheduler): the tasks run in this process, in order.
* ``jobs > 1``: the tasks run on ``jobs`` *spawned* worker processes (not forked, so a
  worker never inherits a parent's threads or locks). A worker ends within a second of
  the process that started it, so a run killed by a signal leaves no orphans computing.
  Every task a worker receives carries ``single_thread = True`` (a mapping's key, or a
  dataclass's field); the task function
  passes it to :func:`single_thread`, so that ``jobs`` workers use ``jobs`` cores rather
  than ``jobs`` times every core.
* ``scheduler="tcp://host:port"``: the tasks are submitted to that dask.distributed
  cluster (the ``[dask]`` extra).

:func:`worker_pool` keeps one pool open for several :func:`run_tasks` calls, so that what
the workers build once (the model banks) serves every pass of a calibration recipe.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import os
import queue
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager, nullcontext
from typing import Any

import numba
from threadpoolctl import threadpool_limits
from tqdm import tqdm

__all__ = ["available_cores", "report_progress", "run_tasks", "single_thread", "worker_pool"]

#: this process's channel to the object bar of the :func:`run_tasks` call whose task runs
#: here (a queue, or None: no bar)
_TICKS: Any = None


def report_progress(kind: str, n: float) -> None:
    """Tell the progress bar of the :func:`run_tasks` call running this task about objects.

    Parameters
    ----------
    kind : {"planned", "done"}
        ``n`` more objects are to be worked on, or ``n`` of them are done.
    n : float
        How many (a fraction where an object's work is shared among several steps).
    """
    if _TICKS is None or not n:
        return
    try:
        _TICKS.put((kind, float(n)))
    except Exception:  # a bar is a courtesy: its channel's failure never fails the work
        pass


def _ticked(fn: Callable[[Any], Any], task: Any, ticks: Any) -> Any:
    """``fn(task)`` with :func:`report_progress` sending to ``ticks``."""
    global _TICKS
    _TICKS = ticks
    try:
        return fn(task)
    finally:
        _TICKS = None


@contextmanager
def _object_bar(bar: tqdm, desc: str, local: bool, wanted: bool) -> Iterator[Any]:
    """A second bar, of objects, under the bar of images ``bar``, fed by the tasks'
    :func:`report_progress` through the channel yielded (None where ``bar`` is off: not
    a terminal, no progress asked, or not ``wanted``). ``local``: the tasks run in this
    process."""
    if bar.disable or not wanted:
        yield None
        return
    manager = None if local else mp.get_context("spawn").Manager()
    ticks = queue.SimpleQueue() if local else manager.Queue()
    objects = tqdm(total=0, desc=f"{desc}: objects", unit="obj", leave=False, position=1,
                   bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} [{elapsed}<{remaining}]")
    stop = threading.Event()

    def drain() -> None:
        while True:
            try:
                kind, n = ticks.get(timeout=0.1)
            except queue.Empty:
                if stop.is_set():
                    return
                continue
            except (EOFError, OSError):  # the manager has gone
                return
            if kind == "planned":
                objects.total += n
                objects.refresh()
            else:
                objects.update(n)

    th = threading.Thread(target=drain, daemon=True, name="pylensfit-progress")
    th.start()
    try:
        yield ticks
    finally:
        stop.set()
        th.join(timeout=5.0)
        objects.close()
        if manager is not None:
            manager.shutdown()


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system reports it)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return max(os.cpu_count() or 1, 1)


def _on_a_worker(task):
    """The task as a worker receives it: with ``single_thread`` set."""
    if dataclasses.is_dataclass(task):
        return dataclasses.replace(task, single_thread=True)
    return {**task, "single_thread": True}


def single_thread(on: bool) -> None:
    """Limit this process to one thread (BLAS, OpenMP and numba) when ``on``.

    Parameters
    ----------
    on : bool
        The task's ``"single_thread"`` entry; ``False`` leaves the thread pools alone.
    """
    if not on:
        return
    threadpool_limits(1)
    numba.set_num_threads(1)


def _exit_with_parent(parent: int) -> None:
    """A pool worker's initializer: the worker ends within a second of the process that
    started it (a run killed by a signal runs no clean-up and would leave its workers
    computing, and holding their memory, for as long as their tasks last)."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="pylensfit-parent-watch").start()


def _executor(jobs: int) -> ProcessPoolExecutor:
    """``jobs`` spawned worker processes that end with this one."""
    return ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                               initializer=_exit_with_parent, initargs=(os.getpid(),))


@contextmanager
def worker_pool(jobs: int, scheduler: str | None = None,
                ) -> Iterator[ProcessPoolExecutor | None]:  # fmt: skip
    """One pool of ``jobs`` local worker processes for several :func:`run_tasks` calls.

    Workers keep what they build between tasks (the model banks: 30-40 s per process
    for bulge+disc banks on two stamp tiers), so a run of several passes pays for it
    once per worker instead of once per pass.

    Parameters
    ----------
    jobs : int
        Number of worker processes.
    scheduler : str, optional
        A dask.distributed scheduler address; then there is no local pool.

    Yields
    ------
    concurrent.futures.ProcessPoolExecutor or None
        The pool; ``None`` (nothing to share) with a scheduler or one job.
    """
    if scheduler or jobs <= 1:
        yield None
        return
    with _executor(jobs) as ex:
        yield ex


def run_tasks(fn: Callable[[Any], Any], tasks: Sequence[Any],
              jobs: int = 1, scheduler: str | None = None, desc: str = "tasks",
              progress: bool = False, pool: ProcessPoolExecutor | None = None,
              objects: bool = False) -> Iterator[tuple[Any, Any]]:  # fmt: skip
    """Run ``fn`` on every task and yield ``(task, result)`` as the tasks finish.

    Parameters
    ----------
    fn : callable
        The task function, a module-level function (it is pickled by reference).
    tasks : sequence of mapping or dataclass
        Its arguments, one per call: a mapping, or a dataclass with a ``single_thread``
        field.
    jobs : int
        Worker processes; 1 runs the tasks in this process, in order.
    scheduler : str, optional
        A dask.distributed scheduler address to submit the tasks to.
    desc : str
        The progress bar's label.
    progress : bool
        Show a tqdm progress bar.
    pool : concurrent.futures.ProcessPoolExecutor, optional
        A pool from :func:`worker_pool` to run the tasks on.
    objects : bool
        With ``progress`` on a terminal, a second bar counts the objects that the tasks
        report (:func:`report_progress`), so that it moves within a task (not with a
        scheduler).

    Yields
    ------
    tuple
        ``(task, result)``; with workers, in the order the tasks finish. An exception
        raised by a task propagates, and the call's remaining tasks are cancelled.
    """
    bar = tqdm(total=len(tasks), desc=desc, unit="image", leave=False,
               disable=None if progress and tasks else True)  # None: on a terminal only
    local = pool is None and not scheduler and (jobs <= 1 or len(tasks) == 1)
    try:
        if not tasks:
            return
        if scheduler:
            # dask.distributed is the optional [dask] extra
            from distributed import Client
            from distributed import as_completed as dask_completed

            with Client(scheduler) as client:
                futs = {client.submit(fn, t, pure=False): t for t in tasks}
                for f in dask_completed(futs):
                    yield futs.pop(f), f.result()  # the cluster's copy freed with it
                    bar.update()
            return
        with _object_bar(bar, desc, local, objects) as ticks:
            if local:
                for t in tasks:
                    yield t, _ticked(fn, t, ticks)
                    bar.update()
                return
            with (nullcontext(pool) if pool is not None else
                  _executor(min(jobs, len(tasks)))) as ex:  # fmt: skip
                futs = {ex.submit(_ticked, fn, _on_a_worker(t), ticks): t for t in tasks}
                try:
                    for f in as_completed(futs):
                        # a finished future is dropped as its result is handed on: kept,
                        # every result would be held twice until the call ends (a
                        # calibration pass keeps its blocks' likelihood grids)
                        yield futs.pop(f), f.result()
                        bar.update()
                finally:  # a failed task: the rest of this call's tasks are not wanted
                    for f in futs:
                        f.cancel()
    finally:
        bar.close()
