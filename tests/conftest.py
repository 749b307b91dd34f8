"""Test-wide settings."""

import compileall
import os
import re
import signal
from collections import Counter
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


# Three workers on two cores (pyproject's addopts). The real-time tests (node processes in real time:
# those marked ``realtime``, and every test of tests/e2e unless marked otherwise) run one at a time on
# one worker; the timed tests that need little CPU (sockets and threads with deadlines, one node alone;
# marked ``deadlines``) one at a time on another; both at the machine's normal priority. Both groups
# wait on the clock for much of their time: the third worker runs the rest from the start at the lowest
# priority, so that it takes only the CPU the timed tests leave and never makes them late, and each of
# the other two joins it, at that priority, once its timed group is done.
GROUPS = ("realtime", "deadlines")
LOW_PRIORITY = 19  # nice value of a worker once its timed group is done
E2E = Path(__file__).parent / "e2e"
PACKAGE = Path(__file__).parents[1] / "atlas_onboard"


def pytest_configure(config: pytest.Config) -> None:
    # The suite starts many ``python -m atlas_onboard`` processes from the source tree. Where
    # the environment forbids writing bytecode (PYTHONDONTWRITEBYTECODE, as in many containers), each
    # of them would compile the package afresh: compiled here once, before the workers start, they
    # all load it (the loader still checks each file's size and time against its source).
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        compileall.compile_dir(PACKAGE, quiet=1)


def _group(item: pytest.Item) -> str | None:
    marked = next((g for g in GROUPS if item.get_closest_marker(g) is not None), None)
    return marked or ("realtime" if E2E in item.path.parents else None)


# A module whose tests share a computation (a module- or class-scoped fixture, a functools cache) has
# its other tests run on one worker, which computes it once: split between the two, each would. Such
# a module stays a smaller unit than either timed group, which are handed out first.
SHARES = re.compile(r"""scope=["'](module|class)["']|functools\.(cache|lru_cache)\b""")


def _shares(path: Path, seen: dict[Path, bool]) -> bool:
    if path not in seen:
        seen[path] = SHARES.search(path.read_text(encoding="utf-8")) is not None
    return seen[path]


@pytest.hookimpl(tryfirst=True)  # before xdist's hook reads the groups
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    groups = {item: _group(item) for item in items}
    timed = Counter(g for g in groups.values() if g is not None)
    seen: dict[Path, bool] = {}
    shared = Counter(item.path for item, g in groups.items() if g is None and _shares(item.path, seen))
    smallest = min(timed.values(), default=len(items) + 1)
    for item, group in groups.items():
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
        elif 0 < shared[item.path] < smallest:
            item.add_marker(pytest.mark.xdist_group(f"module {item.path.relative_to(E2E.parent)}"))


def pytest_runtest_setup(item: pytest.Item) -> None:
    # The two groups are the largest units of work, so each is handed out first, one to a worker, and
    # runs before anything else there: a worker at a test outside them has no timed test to come.
    if os.environ.get("PYTEST_XDIST_WORKER") and _group(item) is None and os.nice(0) < LOW_PRIORITY:
        os.nice(LOW_PRIORITY - os.nice(0))
