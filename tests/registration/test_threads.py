"""A large batch answered in two halves gives what one call gives, and never leaves its worker
reading behind the caller's back."""

import multiprocessing
import threading
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from o3dreg.registration import _threads
from o3dreg.registration._threads import MIN_SPLIT, in_halves


@pytest.fixture
def two_cores(monkeypatch):
    monkeypatch.setattr(_threads, "_usable_cores", lambda: 2)


def test_same_answer_as_one_query(two_cores):
    rng = np.random.default_rng(0)
    sites = rng.random((500, 3))
    points = rng.random((3 * MIN_SPLIT + 1, 3))  # odd: the halves differ in length
    tree = cKDTree(sites)
    e, i = in_halves(lambda p: tree.query(p, k=2), points)
    e1, i1 = tree.query(points, k=2)
    np.testing.assert_array_equal(e, e1)
    np.testing.assert_array_equal(i, i1)


def test_small_batch_stays_on_the_calling_thread(two_cores):
    seen = []
    in_halves(lambda p: (seen.append(threading.current_thread()), p)[1:], np.zeros((10, 3)))
    assert seen == [threading.current_thread()]


def test_one_core_stays_on_the_calling_thread(monkeypatch):
    monkeypatch.setattr(_threads, "_usable_cores", lambda: 1)
    seen = []
    in_halves(lambda p: (seen.append(threading.current_thread()), p)[1:], np.zeros((MIN_SPLIT, 3)))
    assert seen == [threading.current_thread()]


def test_interrupted_caller_waits_for_its_worker(two_cores):
    # The calling thread's half raises (as a Ctrl-C would) while the worker is still busy:
    # the call returns only once the worker is done with the arrays.
    done = threading.Event()

    def query(p):
        if threading.current_thread() is threading.main_thread():
            raise KeyboardInterrupt
        time.sleep(0.2)
        done.set()
        return (p,)

    with pytest.raises(KeyboardInterrupt):
        in_halves(query, np.zeros((MIN_SPLIT, 3)))
    assert done.is_set()


def _child(queue):
    points = np.arange(3 * MIN_SPLIT, dtype=float).reshape(-1, 3)
    (out,) = in_halves(lambda p: (p * 2.0,), points)
    queue.put(bool(np.array_equal(out, points * 2.0)))


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="no fork")
def test_forked_child_makes_its_own_worker(two_cores):
    # The parent's pool exists (its thread does not in a forked child); the child must not
    # hand work to it and wait forever.
    in_halves(lambda p: (p,), np.zeros((MIN_SPLIT, 3)))
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_child, args=(queue,))
    child.start()
    child.join(30)
    assert child.exitcode == 0
    assert queue.get(timeout=5) is True
