"""Named event counters: a rejection counts under its counter name, reads of an unknown name are zero,
snapshots are copies, and increments from several threads are never lost."""

from __future__ import annotations

import threading

from atlas_onboard.core.rejection import Rejection
from atlas_onboard.counters import Counters


def test_a_rejection_counts_under_its_counter_name_and_by_name_alike():
    c = Counters()
    c.inc(Rejection.NON_FINITE)
    c.inc("rejected_non_finite", 2)
    assert c["rejected_non_finite"] == 3
    assert c[Rejection.NON_FINITE] == 3 and c.get(Rejection.NON_FINITE) == 3
    assert c.snapshot() == {"rejected_non_finite": 3}


def test_unknown_names_read_zero_or_the_default_without_being_created():
    c = Counters()
    assert c["never"] == 0 and c.get("never", 7) == 7 and c.get(Rejection.BAD_SIGMA) == 0
    assert c.snapshot() == {} and c.values() == [] and list(c.items()) == []


def test_update_counts_each_name_once_in_order_of_arrival():
    c = Counters()
    c.update(["a", "b", "a", Rejection.BAD_SIGMA])
    assert c.snapshot() == {"a": 2, "b": 1, "rejected_bad_sigma": 1}
    assert c.values() == [2, 1, 1]
    assert list(c.items()) == [("a", 2), ("b", 1), ("rejected_bad_sigma", 1)]
    assert repr(c) == "Counters({'a': 2, 'b': 1, 'rejected_bad_sigma': 1})"


def test_a_snapshot_is_a_copy_that_later_counts_do_not_change():
    c = Counters()
    c.inc("x")
    snap = c.snapshot()
    c.inc("x")
    snap["x"] = 100
    assert c["x"] == 2


def test_increments_from_several_threads_are_never_lost():
    c = Counters()
    n, threads = 20_000, 4

    def work() -> None:
        for _ in range(n):
            c.inc("x")

    workers = [threading.Thread(target=work) for _ in range(threads)]
    for t in workers:
        t.start()
    for t in workers:
        t.join()
    assert c["x"] == n * threads
