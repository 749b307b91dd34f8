"""Fixtures of the MAVLink tests."""

import contextlib

import pytest


@pytest.fixture
def closing():
    """Close every link or socket registered with it at the end of the test."""
    things: list = []
    yield things.append
    for t in things:
        with contextlib.suppress(Exception):
            t.close()
