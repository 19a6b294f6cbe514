"""An ordered map over forked worker processes with a bounded number of tasks in flight."""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import multiprocessing
import os
import signal
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

T = TypeVar("T")

#: Tasks submitted ahead per worker: keeps the workers busy while bounding the results held.
READ_AHEAD = 2

#: Seconds a worker is given to end after SIGTERM before it is killed.
STOP_GRACE = 2.0

_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _worker_init(parent: int) -> None:
    """Make a worker end with its parent rather than outlive it.

    Ctrl-C is left to the parent, which ends its workers (a worker interrupted while waiting for
    work would print a traceback); SIGTERM gets its default action back (the command line's
    handler raises an exception, which a worker would report and carry on); on Linux the kernel
    kills the worker when the parent dies even by SIGKILL, where no cleanup of the parent runs.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    with contextlib.suppress(OSError, AttributeError):  # not Linux: the parent's cleanup alone
        ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """End the pool's workers now. ``shutdown`` would let each finish its task first, and a worker
    left behind by a parent that stops waits for work for ever, holding its memory."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        p.terminate()
    for p in procs:
        p.join(STOP_GRACE)
        if p.is_alive():
            p.kill()
            p.join()


def ordered_map(fn: Callable[..., T], tasks: Iterable[tuple], workers: int = 1) -> Iterator[T]:
    """``fn(*task)`` for every task, yielded in task order (so an error is raised in that order).

    With ``workers`` > 1 the calls run in forked processes, which inherit the module state set
    before this call (nothing large is pickled) and must not use torch's thread pool (its OpenMP
    pool is not fork-safe): a task that uses torch sets it to one thread first. At most ``READ_AHEAD * workers`` tasks are in flight, so memory holds a bounded
    number of results however many tasks there are. An error, Ctrl-C or SIGTERM (through the
    command line's handler) in the caller, or closing the iterator early, ends the workers at once.
    """
    if workers <= 1:
        yield from (fn(*t) for t in tasks)
        return
    todo = iter(tasks)
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"),
                               initializer=_worker_init, initargs=(os.getpid(),))
    try:
        pending: deque[Future] = deque(pool.submit(fn, *t) for t in itertools.islice(todo, READ_AHEAD * workers))
        while pending:
            result = pending.popleft().result()
            pending.extend(pool.submit(fn, *t) for t in itertools.islice(todo, 1))
            yield result
    except BaseException:
        _stop_workers(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
