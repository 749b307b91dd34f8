"""Test-wide settings."""

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

# README's `-n 2 --dist loadgroup`: a test file goes to one worker whole (its module-wide runs are made
# once), and the files that run real-time simulations or several node processes go to one worker one
# after another: two of them at once would share the cores their real-time nodes need.
REALTIME_FILES = frozenset({
    "tests/test_sim.py", "tests/test_cli_signals.py", "tests/sim/test_hard.py", "tests/sim/test_demo.py",
    "tests/sim/test_prerender.py", "tests/e2e/test_record.py", "tests/e2e/test_refine.py",
    "tests/e2e/test_replay.py", "tests/mapping/test_map.py",
})  # fmt: skip
_ROOT = Path(__file__).resolve().parent.parent


def pytest_configure(config: pytest.Config) -> None:
    # pytest-xdist's mark, known also where the suite runs without it (one file, a venv without the extra).
    config.addinivalue_line("markers", "xdist_group(name): tests that run in one worker, one after another")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        path = item.path.resolve().relative_to(_ROOT).as_posix()
        item.add_marker(pytest.mark.xdist_group("realtime" if path in REALTIME_FILES else path))
