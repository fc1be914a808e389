"""``medseg.threads.thread_map``: results in the items' order, whatever the threads."""

from __future__ import annotations

import multiprocessing
import sys
import threading
import time

import pytest

from medseg.threads import thread_map


@pytest.mark.parametrize("n_jobs", [None, 1, 2, -1])
def test_results_come_in_the_items_order(n_jobs):
    def slow_first(i):  # the early items finish last on two threads
        time.sleep(0.02 * (5 - i))
        return i * i

    assert thread_map(slow_first, range(5), n_jobs) == [0, 1, 4, 9, 16]


def test_one_job_or_one_item_runs_on_the_calling_thread():
    def name(_):
        return threading.current_thread().name

    caller = threading.current_thread().name
    assert thread_map(name, range(3), 1) == [caller] * 3
    assert thread_map(name, [0], 2) == [caller]
    assert thread_map(name, [], 2) == []
    on_two = thread_map(name, range(4), 2)
    assert all(n.startswith("medseg") for n in on_two)


def test_an_error_in_one_item_reaches_the_caller():
    def fails_on_two(i):
        if i == 2:
            raise ValueError("item 2")
        return i

    with pytest.raises(ValueError, match="item 2"):
        thread_map(fails_on_two, range(4), 2)


def _square_on_two_threads(queue) -> None:
    queue.put(thread_map(lambda i: i * i, range(4), 2))


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_a_forked_child_gets_threads_of_its_own():
    """The parent's pool is in use before the fork; the child's thread_map still finishes
    (with the parent's pool object it would wait forever on threads it does not have)."""
    assert thread_map(lambda i: i, range(4), 2) == [0, 1, 2, 3]
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_square_on_two_threads, args=(queue,))
    child.start()
    child.join(timeout=60)
    if child.is_alive():
        child.kill()
        pytest.fail("thread_map in a forked child hung")
    assert queue.get(timeout=5) == [0, 1, 4, 9]
