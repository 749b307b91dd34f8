"""Test-wide settings."""

import signal

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
