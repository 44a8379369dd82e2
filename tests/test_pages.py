"""NumPy's huge-page advice is off inside the registrations and the caller's setting comes back."""

import threading

import numpy as np
import pytest

from o3dreg import _pages
from o3dreg.app.synthetic import synthetic_form

pytestmark = pytest.mark.skipif(
    _pages._set_madvise_hugepage is None, reason="this NumPy has no huge-page switch"
)


def advice() -> bool:
    """The current setting (the switch returns the previous one; put it back)."""
    current = _pages._set_madvise_hugepage(True)
    _pages._set_madvise_hugepage(current)
    return bool(current)


@pytest.fixture(params=[True, False])
def caller_setting(request):
    before = _pages._set_madvise_hugepage(request.param)
    yield request.param
    _pages._set_madvise_hugepage(before)


def test_registrations_switch_it_off_and_restore_the_callers(caller_setting):
    import o3dreg

    source, target = synthetic_form("sphere", 300), synthetic_form("cube", 1000)
    seen = []
    o3dreg.registration_elastic(
        source,
        target,
        init=np.eye(4),
        levels=[o3dreg.ElasticLevel(2)],
        callback=lambda report: seen.append(advice()),
    )
    assert seen == [False]
    assert advice() is caller_setting
    o3dreg.registration_rigid(source, target)
    assert advice() is caller_setting


def test_nested_and_concurrent_uses_restore_it_once(caller_setting):
    with _pages.small_pages():
        with _pages.small_pages():
            assert advice() is False
        assert advice() is False  # the inner exit does not restore while the outer runs
    assert advice() is caller_setting

    inside = threading.Barrier(3)
    leave = threading.Event()

    def worker():
        with _pages.small_pages():
            inside.wait()
            leave.wait()

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    inside.wait()  # both threads are inside
    assert advice() is False
    leave.set()
    for t in threads:
        t.join()
    assert advice() is caller_setting


def test_an_exception_inside_restores_it(caller_setting):
    with pytest.raises(RuntimeError):
        with _pages.small_pages():
            raise RuntimeError("boom")
    assert advice() is caller_setting
