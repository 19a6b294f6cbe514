"""Views rendered side by side on CPU threads.

A trained run's renders are small ops (a view's samples, one field lookup at a time) that
torch's intra-op pool barely speeds up: on two cores a view renders no faster with two intra-op
threads than with one. Rendering *views* on separate Python threads (torch releases the GIL
inside its ops), each op on one thread, keeps every core busy instead
(``benchmarks/bench_render_threads.py`` measures it). Every view is computed on one thread
whatever the number of workers, so results do not depend on it.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence, TypeVar

import torch

T = TypeVar("T")
R = TypeVar("R")


def render_workers(device: torch.device, num_items: int) -> int:
    """Threads that :func:`map_views` uses: as many as torch's intra-op threads on CPU (one per
    core by default; ``OMP_NUM_THREADS`` / ``torch.set_num_threads`` lower it), one on other
    devices (their ops are queued on one stream), never more than there are items."""
    if device.type != "cpu":
        return 1
    return max(1, min(torch.get_num_threads(), num_items))


def map_views(fn: Callable[[T], R], items: Sequence[T], device: torch.device, desc: str | None = None) -> list[R]:
    """``[fn(x) for x in items]``, on CPU spread over :func:`render_workers` threads, each running
    torch ops on one intra-op thread (restored afterwards). ``fn`` must only read shared state
    (a trained run is read-only while it renders). ``desc``: show a progress bar with that label.
    The first error raised by ``fn`` is raised here, once the views already started finish (the
    rest are not started)."""
    from tqdm import tqdm

    bar = tqdm(total=len(items), desc=desc, disable=desc is None or not items, dynamic_ncols=True)
    workers = render_workers(device, len(items))
    before = torch.get_num_threads()
    try:
        if workers == 1:
            out = []
            for x in items:
                out.append(fn(x))
                bar.update()
            return out
        torch.set_num_threads(1)  # one per worker; global in torch, so restored below

        def one(x: T) -> R:
            r = fn(x)
            bar.update()
            return r

        pool = ThreadPoolExecutor(workers, thread_name_prefix="render")
        try:
            return list(pool.map(one, items))
        finally:  # on an error or an interrupt, views not yet started are dropped
            pool.shutdown(wait=True, cancel_futures=True)
    finally:
        torch.set_num_threads(before)
        bar.close()
