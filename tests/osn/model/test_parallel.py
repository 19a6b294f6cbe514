"""map_views: views side by side on CPU threads, one intra-op thread each, in order."""

from __future__ import annotations

import threading
import time

import pytest
import torch

from osn.model.parallel import map_views, render_workers

CPU = torch.device("cpu")


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_views_run_on_two_threads_in_order_with_one_op_thread_each(two_threads) -> None:
    seen: list[tuple[str, int]] = []

    def fn(x: int) -> int:
        time.sleep(0.02)  # long enough that both workers take items
        seen.append((threading.current_thread().name, torch.get_num_threads()))
        return x * x

    assert render_workers(CPU, 10) == 2 and render_workers(CPU, 1) == 1
    assert render_workers(torch.device("meta"), 10) == 1  # a non-CPU device: one thread
    assert map_views(fn, list(range(10)), CPU) == [x * x for x in range(10)]
    assert len({name for name, _ in seen}) == 2 and all(name.startswith("render") for name, _ in seen)
    assert {n for _, n in seen} == {1}
    assert torch.get_num_threads() == 2  # restored
    assert map_views(fn, [], CPU) == []


def test_an_error_in_one_view_is_raised_and_later_views_are_not_started(two_threads) -> None:
    started: list[int] = []

    def fn(x: int) -> int:
        started.append(x)
        time.sleep(0.02)
        if x == 1:
            raise RuntimeError("view 1 failed")
        return x

    with pytest.raises(RuntimeError, match="view 1 failed"):
        map_views(fn, list(range(200)), CPU)
    assert len(started) < 100 and torch.get_num_threads() == 2  # 100 would take the workers 1 s
