"""The simulated autopilot's landing: centres and descends on exact targets in each form, refuses the
other form, aborts and climbs when the target is lost, and lands once it is back."""

import math

import numpy as np
import pytest

from atlas_onboard.mavlink.landing import ardupilot_landing_target_fields, px4_landing_target_fields
from atlas_onboard.sim.lander import Lander, LanderSettings, Phase

PAD = np.array([1.0, -0.5, 0.1])  # ENU


def exact_fields(form, lander):
    """The message a perfect node would send now (the vehicle's true pose)."""
    if form == "px4":
        return px4_landing_target_fields(0, PAD[1], PAD[0], -PAD[2], (1.0, 0.0, 0.0, 0.0))
    rel = lander.attitude.inv().apply(PAD - lander.p_m)
    x, y, z = rel[0], -rel[1], -rel[2]
    return ardupilot_landing_target_fields(0, x, y, z, math.sqrt(x * x + y * y + z * z), math.atan(y / z),
                                           math.atan(-x / z))  # fmt: skip


def fly(form, seconds, gap=(math.inf, math.inf), rate_hz=20.0):
    lander = Lander(LanderSettings(form), np.array([0.0, 0.0, 1.5]), yaw_rad=0.7)
    dt, next_msg, zs = 0.01, 0.0, []
    for k in range(round(seconds / dt)):
        t = k * dt
        if t >= next_msg and not gap[0] <= t < gap[1] and lander.phase is not Phase.LANDED:
            lander.on_target(exact_fields(form, lander), t, lander.p_m.copy())
            next_msg = t + 1.0 / rate_hz
        lander.step(t, dt, lander.p_m.copy(), PAD[2])
        zs.append(lander.p_m[2])
    return lander, np.array(zs)


@pytest.mark.parametrize("form", ["px4", "ardupilot"])
def test_lands_on_the_target(form):
    lander, _ = fly(form, 12.0)
    assert lander.phase is Phase.LANDED and lander.aborts == 0
    assert np.linalg.norm(lander.touchdown_m[:2] - PAD[:2]) < 0.01 and lander.touchdown_m[2] == PAD[2]


def test_the_other_form_is_refused():
    lander = Lander(LanderSettings("px4"), np.array([0.0, 0.0, 1.5]))
    lander.on_target(ardupilot_landing_target_fields(0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0), 0.0, lander.p_m)
    lander.step(0.1, 0.1, lander.p_m, 0.0)
    assert lander.refused == 1 and lander.phase is Phase.WAIT and lander.target_m is None


def test_a_lost_target_aborts_the_descent_and_the_landing_resumes():
    # Lost from 2.0 s to 4.5 s in the descent (1 s timeout): the vehicle climbs, then lands once back.
    lander, zs = fly("px4", 16.0, gap=(2.0, 4.5))
    t = np.arange(len(zs)) * 0.01
    assert lander.aborts == 1 and lander.phase is Phase.LANDED
    lowest_before = zs[(t > 2.0) & (t < 3.0)].min()
    assert zs[(t > 3.0) & (t < 4.5)].max() > lowest_before + 0.3  # climbed while lost
    assert np.linalg.norm(lander.touchdown_m[:2] - PAD[:2]) < 0.01
