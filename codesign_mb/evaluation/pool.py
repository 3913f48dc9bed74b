"""The one local process pool: every parallel episode, trial and figure point runs through it.

Workers are started with ``spawn`` (forking a process that holds threads, as MuJoCo, CasADi,
torch and Ray do, is unsafe), run one BLAS/OpenMP thread each (the workers already use every
core), and end quietly on Ctrl-C (the driver reports the interruption once). A worker that
dies (killed from outside, out of memory) costs nothing but time: tasks are pure functions of
their arguments, so the missing ones are rerun in a fresh pool, at most ``max_restarts`` times.
Workers never outlive their driver: on Linux each asks the kernel for ``SIGKILL`` when the
driver dies (``prctl(PR_SET_PDEATHSIG)``; elsewhere a thread watches the parent's pid), so
killing the driver, even with ``SIGKILL``, ends them; and a driver that stops early (an error,
Ctrl-C, a consumer that stops reading) ends its workers at once instead of letting them finish
their episodes. A script calling :func:`imap` with ``workers > 1`` needs the usual
``if __name__ == "__main__":`` guard.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from multiprocessing import get_context
from typing import Any, TypeVar

__all__ = ["check_workers", "die_with_parent", "imap", "single_threaded_worker"]

T = TypeVar("T")
R = TypeVar("R")


def single_threaded_worker() -> None:
    """One OpenMP/BLAS/torch thread in this process (a pool worker's first act).

    Workers already use every core; torch's default of one intra-op thread per core makes
    the small networks of the learned components about 20x slower when the workers share
    the cores (SAC's actor: 6.6 ms a call instead of 0.3 ms on 2 cores). An explicit
    ``OMP_NUM_THREADS`` in the environment is kept.
    """
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(variable, "1")
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


def _exit_interrupted(signum: int, frame: Any) -> None:
    raise SystemExit(130)


_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent() -> None:
    """End this process when its parent dies (a pool worker's second act).

    Linux: the kernel sends ``SIGKILL`` when the thread that started this process exits
    (``prctl(PR_SET_PDEATHSIG)``; the pool starts its workers from the thread calling
    :func:`imap`). Elsewhere a daemon thread checks the parent's pid every second. A
    parent already gone by then ends this process at once.
    """
    parent = multiprocessing.parent_process()
    expected = parent.pid if parent is not None else os.getppid()
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            _watch_parent(expected)  # not permitted (a sandbox): poll instead
    else:
        _watch_parent(expected)
    if os.getppid() != expected:  # the parent died before the request took effect
        os._exit(1)


def _watch_parent(pid: int | None) -> None:
    def watch() -> None:
        while os.getppid() == pid:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def _init_worker(initializer: Callable[..., None] | None, initargs: tuple[Any, ...]) -> None:
    single_threaded_worker()
    die_with_parent()
    signal.signal(signal.SIGINT, _exit_interrupted)
    if initializer is not None:
        initializer(*initargs)


@contextmanager
def _starting_deaf() -> Iterator[None]:
    """Ignore ``SIGINT`` while workers are started: a spawned process inherits an ignored
    signal, so a Ctrl-C during its start-up (seconds of imports, when the other worker may have
    finished episodes already) does not print a ``KeyboardInterrupt`` traceback; its
    initializer then installs the quiet exit. The driver ignores Ctrl-C for the few
    milliseconds the ``fork`` and ``exec`` take (only the main thread can set a handler)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def check_workers(workers: int | None, tasks: int) -> int:
    """Validated worker count: default one per CPU, at most ``tasks``, at least 1."""
    if workers is None:
        workers = os.cpu_count() or 1
    if isinstance(workers, bool) or int(workers) != workers or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    return max(1, min(int(workers), max(tasks, 1)))


def imap(
    fn: Callable[..., R],
    tasks: Sequence[tuple[Any, ...]],
    *,
    workers: int | None = None,
    initializer: Callable[..., None] | None = None,
    initargs: tuple[Any, ...] = (),
    max_restarts: int = 2,
) -> Iterator[tuple[int, R]]:
    """Run ``fn(*task)`` for every task; yield ``(task index, result)`` as each completes.

    ``workers == 1`` runs in this process, in order (``initializer`` is not called: the
    caller's process is already set up). Results come in completion order otherwise.
    """
    n_workers = check_workers(workers, len(tasks))
    if n_workers == 1:
        for i, task in enumerate(tasks):
            yield i, fn(*task)
        return
    pending = set(range(len(tasks)))
    restarts = 0
    while pending:
        with _starting_deaf():  # the workers start (at the first submits) ignoring Ctrl-C
            pool = ProcessPoolExecutor(
                max_workers=n_workers,
                mp_context=get_context("spawn"),
                initializer=_init_worker,
                initargs=(initializer, initargs),
            )
            futures: dict[Future[R], int] = {pool.submit(fn, *tasks[i]): i for i in sorted(pending)}
        finished = False
        try:
            remaining = set(futures)
            while remaining:
                done, remaining = wait(remaining, return_when=FIRST_COMPLETED)
                for future in sorted(done, key=futures.__getitem__):
                    result = future.result()
                    pending.discard(futures[future])
                    yield futures[future], result
            finished = True
        except BrokenProcessPool:
            restarts += 1
            if restarts > max_restarts:
                raise
            warnings.warn(
                f"a worker process died; rerunning {len(pending)} tasks in a new pool",
                RuntimeWarning,
                stacklevel=2,
            )
        finally:  # on an error or an abandoned generator, stop at once
            _shutdown(pool, finished)


def _shutdown(pool: ProcessPoolExecutor, finished: bool) -> None:
    """Shut ``pool`` down; if not ``finished``, end its workers now (their results are lost
    anyway) rather than wait, at exit, for their running tasks."""
    # The executor's own table of its processes (Python 3.14 adds terminate_workers()).
    processes = [] if finished else list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=finished, cancel_futures=not finished)
    for process in processes:
        if process.is_alive():
            process.terminate()
