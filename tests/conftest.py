"""Test-wide settings."""

import os
import signal
from pathlib import Path

import pytest
from hypothesis import settings

# Tests never assert a time: hypothesis's per-example deadline would, and a loaded 2-core machine
# misses it now and then. The number of examples stays each test's own.
settings.register_profile("atlas", deadline=None)
settings.load_profile("atlas")

# A suite started in the background by a shell without job control (`pytest &` in a script, some CI
# runners) inherits SIGINT ignored, and so would every process it starts: the tests that press Ctrl-C
# on a command would wait for it in vain. Ctrl-C as a terminal delivers it, whoever started the suite.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


# Two workers (pyproject's addopts): the real-time tests (node processes, sockets and threads with
# deadlines: every test of tests/e2e, and those marked ``realtime``) run one at a time on one worker, at
# the machine's normal priority; everything else runs on the other, at the lowest priority, so that it
# takes only the CPU the real-time tests leave and never makes them late.
REALTIME_GROUP = "realtime"
LOW_PRIORITY = 19  # nice value of the other worker
E2E = Path(__file__).parent / "e2e"


def _realtime(item: pytest.Item) -> bool:
    return item.get_closest_marker("realtime") is not None or E2E in item.path.parents


@pytest.hookimpl(tryfirst=True)  # before xdist's hook reads the groups
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if _realtime(item):
            item.add_marker(pytest.mark.xdist_group(REALTIME_GROUP))


def pytest_runtest_setup(item: pytest.Item) -> None:
    # The real-time group is the largest unit of work, so it is handed out first and runs before
    # anything else on its worker: a worker at a test outside it has no real-time test to come.
    if os.environ.get("PYTEST_XDIST_WORKER") and not _realtime(item) and os.nice(0) < LOW_PRIORITY:
        os.nice(LOW_PRIORITY - os.nice(0))
