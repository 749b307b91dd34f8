"""The bench checks on synthetic relay data: each says PASS on a right setup and FAIL, naming the cause,
on the wrong one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.mavlink.autopilot import MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4
from atlas_onboard.mavlink.samples import AttitudeSample, PositionSample, Tap, VisionSample
from atlas_onboard.preflight.checks import (
    Verdict,
    check_delay,
    check_local_position,
    check_origin,
    check_peers,
    check_rate,
    check_tilt,
    check_timesync,
    check_yaw,
)

T0 = 1_800_000_000.0


def vision(n: int = 60, hz: float = 30.0, latency_s: float = 0.03, xyz=(0.2, -0.5, -0.9), R=None) -> list[VisionSample]:
    x, y, z, w = (R or Rotation.identity()).as_quat()
    return [VisionSample(T0 + k / hz + latency_s, round((T0 + k / hz) * 1e6), xyz, (w, x, y, z)) for k in range(n)]


def attitude(n: int = 80, hz: float = 40.0, rpy=(0.0, 0.0, 0.0)) -> list[AttitudeSample]:
    return [AttitudeSample(T0 + k / hz, *rpy) for k in range(n)]


@pytest.mark.parametrize(
    ("latency_ms", "param_ms", "synced", "verdict", "words"),
    [
        (30.0, 200.0, True, Verdict.FAIL, "200 ms is longer than the whole"),
        (30.0, 25.0, True, Verdict.PASS, ""),
        (30.0, 0.0, True, Verdict.PASS, ""),  # converged TIMESYNC: the stamp covers most of it
        (80.0, 0.0, False, Verdict.FAIL, "much shorter"),  # not converged: PX4 stamps on arrival
    ],
)
def test_px4_delay_against_the_measured_latency(latency_ms, param_ms, synced, verdict, words) -> None:
    c = check_delay(vision(latency_s=latency_ms / 1000), {"EKF2_EV_DELAY": param_ms}, MAV_AUTOPILOT_PX4, synced)
    assert c.verdict is verdict and words in c.detail
    assert f"capture to autopilot {latency_ms:.0f} ms" in c.detail
    if verdict is Verdict.FAIL:
        assert f"about {latency_ms:.0f} ms" in c.fix


def test_ardupilot_delay_is_checked_both_ways_and_unanswered_is_a_skip() -> None:
    v = vision(latency_s=0.06)
    assert check_delay(v, {"VISO_DELAY_MS": 10.0}, MAV_AUTOPILOT_ARDUPILOTMEGA, False).verdict is Verdict.FAIL
    assert check_delay(v, {"VISO_DELAY_MS": 55.0}, MAV_AUTOPILOT_ARDUPILOTMEGA, False).verdict is Verdict.PASS
    assert check_delay(v, {}, MAV_AUTOPILOT_ARDUPILOTMEGA, False).verdict is Verdict.SKIP


def test_local_position_following_in_swapped_axes_is_named() -> None:
    v = vision(xyz=(0.2, -0.5, -0.9))
    same = [PositionSample(s.arrival_s + 0.001, s.xyz_ned_m) for s in v[::3]]
    assert check_local_position(v, same).verdict is Verdict.PASS
    swapped = [PositionSample(s.arrival_s + 0.001, (-0.5, 0.2, -0.9)) for s in v[::3]]
    c = check_local_position(v, swapped)
    assert c.verdict is Verdict.FAIL and "its x is vision's y, its y is vision's x" in c.detail
    assert check_local_position(v, []).verdict is Verdict.SKIP


def test_rate_and_gaps() -> None:
    assert check_rate(vision(hz=30.0), 2.0, MAV_AUTOPILOT_PX4).verdict is Verdict.PASS
    assert check_rate(vision(hz=5.0), 12.0, MAV_AUTOPILOT_PX4).verdict is Verdict.FAIL
    v = vision(n=90, hz=30.0)
    gappy = v[:30] + [VisionSample(s.arrival_s + 0.5, s.usec, s.xyz_ned_m, s.q_ned_frd_wxyz) for s in v[30:]]
    assert check_rate(gappy, 3.5, MAV_AUTOPILOT_PX4).verdict is Verdict.FAIL
    assert check_rate([], 3.0, MAV_AUTOPILOT_PX4).verdict is Verdict.FAIL


def test_timesync_and_origin() -> None:
    assert check_timesync(Tap(autopilot=MAV_AUTOPILOT_PX4)).verdict is Verdict.FAIL
    assert check_timesync(Tap(autopilot=MAV_AUTOPILOT_PX4, timesync_requests=10)).verdict is Verdict.FAIL
    ok = Tap(autopilot=MAV_AUTOPILOT_PX4, timesync_requests=10, timesync_answers=9)
    assert check_timesync(ok).verdict is Verdict.PASS
    assert check_timesync(Tap(autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA)).verdict is Verdict.SKIP
    assert check_origin(Tap(autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA)).verdict is Verdict.FAIL
    assert check_origin(Tap(autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA, origin=(47.0, 8.0, 0.0))).verdict is Verdict.PASS
    assert check_origin(Tap(autopilot=MAV_AUTOPILOT_PX4)).verdict is Verdict.PASS
    high = check_origin(Tap(autopilot=MAV_AUTOPILOT_PX4, origin=(47.0, 8.0, 489.4), params={"EKF2_HGT_REF": 3}))
    assert high.verdict is Verdict.FAIL and "489.4" in high.detail


def test_yaw_only_when_the_autopilot_takes_it_from_vision() -> None:
    v = vision(R=Rotation.from_euler("z", 90, degrees=True))
    a = attitude(rpy=(0.0, 0.0, np.radians(90.0)))
    assert check_yaw(v, a, None).verdict is Verdict.SKIP and check_yaw(v, a, False).verdict is Verdict.SKIP
    assert check_yaw(v, a, True).verdict is Verdict.PASS
    off = check_yaw(v, attitude(rpy=(0.0, 0.0, 0.0)), True)
    assert off.verdict is Verdict.FAIL and "+90 deg" in off.detail


def test_peer_skew_from_the_node_log() -> None:
    from atlas_onboard.config import NodeConfig
    from atlas_onboard.config.settings import LinkConfig

    node = NodeConfig(entity="d1", system_id=1, peers=(LinkConfig(url="udpin:0.0.0.0:14600"),))
    checks = check_peers(node, "x WARNING y: peer system 7: capture stamps and arrival disagree by 412 ms; sync")
    assert [c.verdict for c in checks] == [Verdict.FAIL, Verdict.FAIL]
    assert "system 7 +412 ms" in checks[1].detail and "udpin:0.0.0.0:14600" in checks[0].detail
    assert [c.verdict for c in check_peers(NodeConfig(entity="d1", system_id=1), "")] == [Verdict.SKIP] * 2


def _pair(rpy_deg) -> tuple[Rotation, Rotation]:
    R = Rotation.from_euler("ZYX", np.atleast_2d(rpy_deg)[:, ::-1], degrees=True)
    return R, R


def test_tilt_signs() -> None:
    still = _pair([0.0, 0.0, 30.0])
    nose_down = _pair([0.0, -20.0, 30.0])  # roll, pitch, yaw (FRD: nose down is negative pitch)
    assert check_tilt("nose down", 1, -1.0, still, nose_down).verdict is Verdict.PASS
    flipped = (nose_down[0], _pair([0.0, 20.0, 30.0])[1])
    c = check_tilt("nose down", 1, -1.0, still, flipped)
    assert c.verdict is Verdict.FAIL and "opposite sign" in c.detail
    swapped = (nose_down[0], _pair([20.0, 0.0, 30.0])[1])
    c = check_tilt("nose down", 1, -1.0, still, swapped)
    assert c.verdict is Verdict.FAIL and "moved its roll" in c.detail
    assert check_tilt("nose down", 1, -1.0, still, still).verdict is Verdict.SKIP
