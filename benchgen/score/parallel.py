"""An ordered map over forked worker processes with a bounded number of tasks in flight."""

from __future__ import annotations

import itertools
import multiprocessing
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

T = TypeVar("T")

#: Tasks submitted ahead per worker: keeps the workers busy while bounding the results held.
READ_AHEAD = 2


def ordered_map(fn: Callable[..., T], tasks: Iterable[tuple], workers: int = 1) -> Iterator[T]:
    """``fn(*task)`` for every task, yielded in task order (so an error is raised in that order).

    With ``workers`` > 1 the calls run in forked processes, which inherit the module state set
    before this call (nothing large is pickled) and must not use torch (its OpenMP pool is not
    fork-safe). At most ``READ_AHEAD * workers`` tasks are in flight, so memory holds a bounded
    number of results however many tasks there are.
    """
    if workers <= 1:
        yield from (fn(*t) for t in tasks)
        return
    todo = iter(tasks)
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
        pending: deque[Future] = deque(pool.submit(fn, *t) for t in itertools.islice(todo, READ_AHEAD * workers))
        try:
            while pending:
                result = pending.popleft().result()
                pending.extend(pool.submit(fn, *t) for t in itertools.islice(todo, 1))
                yield result
        finally:
            for f in pending:
                f.cancel()
