"""Test-wide settings."""

from hypothesis import settings

# Tests never assert a time: hypothesis's per-example deadline would, and a loaded 2-core machine
# misses it now and then. The number of examples stays each test's own.
settings.register_profile("atlas", deadline=None)
settings.load_profile("atlas")
