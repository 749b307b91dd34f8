"""The landing scenarios, closed loop: the node's decision and messages fly the simulated autopilot
onto the true landing point; a lost target is never sent stale, and the autopilot aborts meanwhile."""

import pytest

from atlas_onboard.errors import AtlasError
from atlas_onboard.sim.landing import run


@pytest.mark.parametrize(("name", "form", "limit_m"), [("land-pad", "px4", 0.03), ("land-rover", "ardupilot", 0.08)])
def test_touchdown_on_the_true_landing_point(name, form, limit_m):
    r = run(name, seed=5, form=form)
    assert r.touchdown_error_m is not None and r.touchdown_error_m < limit_m
    assert r.sent > 10 and r.stale_sent == 0 and r.aborts == 0


def test_the_target_lost_for_two_seconds_mid_descent():
    r = run("land-pad", seed=6, form="px4", gap_s=(1.5, 3.5))
    assert r.stale_sent == 0 and r.aborts == 1  # nothing old went out; the autopilot climbed meanwhile
    assert r.touchdown_error_m is not None and r.touchdown_error_m < 0.03


def test_unknown_scenario():
    with pytest.raises(AtlasError, match="land-pad"):
        run("land-nowhere")
