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


@pytest.fixture(params=["fast", "pymavlink"])
def framing_mode(request, monkeypatch):
    """Run a test with the framing fast path and with pymavlink's own parser (its off switch)."""
    from atlas_onboard.mavlink import framing

    monkeypatch.setattr(framing, "FAST", request.param == "fast")
    return request.param
