"""The autopilot's identity: pinned to the configured system id's component 1 (another system's only after a
wait without it), never replaced by another HEARTBEAT; ATTITUDE and GPS_GLOBAL_ORIGIN only from it; an
ATTITUDE stamped ahead of the autopilot's clock refused; its body rates (FRD -> FLU) kept for the cameras."""

import math
import time
from types import SimpleNamespace

import numpy as np

from atlas_onboard.config import AutopilotConfig, LinkConfig, NodeConfig
from atlas_onboard.mavlink.autopilot_link import AUTOPILOT_WAIT_NS, AutopilotLink
from tests.mavlink.loopback import D, free_port

PX4, ARDUPILOT = 12, 3
NS = 1_000_000_000


class Clock:
    """A wall clock (s, called) and a monotonic one (ns, ``mono_ns``) that advance together, by hand."""

    def __init__(self) -> None:
        self.s = 1_700_000_000.0

    def __call__(self) -> float:
        return self.s

    def mono_ns(self) -> int:
        return round((self.s - 1_700_000_000.0) * NS) + NS


def _link(clock=None) -> AutopilotLink:
    config = NodeConfig(
        entity="d1", system_id=1, autopilot=AutopilotConfig(LinkConfig(f"udpout:127.0.0.1:{free_port()}"))
    )
    if clock is None:
        return AutopilotLink(config, 197, time.time)
    return AutopilotLink(config, 197, clock, clock.mono_ns)


def _from(msg, system: int, component: int):
    """``msg`` as received from (system, component): packed and parsed back."""
    return D.MAVLink(None).parse_buffer(msg.pack(D.MAVLink(None, srcSystem=system, srcComponent=component)))[0]


def _heartbeat(system, component=1, autopilot=PX4):
    return _from(D.MAVLink_heartbeat_message(2, autopilot, 0, 0, 3, 3), system, component)


def test_another_systems_heartbeat_never_becomes_the_autopilot():
    ap = _link()
    ap._on_message(None, _heartbeat(2, autopilot=ARDUPILOT), 0)  # behind a router: another vehicle, first
    assert ap.autopilot_system is None
    ap._on_message(None, _heartbeat(1, 2), 1)  # the vehicle's gimbal: never the autopilot
    ap._on_message(None, _heartbeat(1), 2)
    assert (ap.autopilot_system, ap.autopilot_component, ap.autopilot_type) == (1, 1, PX4)
    for k in range(5):
        ap._on_message(None, _heartbeat(2, autopilot=ARDUPILOT), 10 * NS + k)
    assert (ap.autopilot_system, ap.autopilot_component, ap.autopilot_type) == (1, 1, PX4)
    assert ap.counters["heartbeat_not_from_autopilot"] == 6


def test_another_system_is_taken_only_after_the_wait_without_the_configured_one():
    ap = _link()
    ap._on_message(None, _heartbeat(7), 0)
    ap._on_message(None, _heartbeat(7), AUTOPILOT_WAIT_NS - 1)
    assert ap.autopilot_system is None
    ap._on_message(None, _heartbeat(7), AUTOPILOT_WAIT_NS)
    assert (ap.autopilot_system, ap.autopilot_component) == (7, 1)
    ap._on_message(None, _heartbeat(1), AUTOPILOT_WAIT_NS + 1)  # pinned for the link's life
    assert ap.autopilot_system == 7


def test_origin_and_attitude_count_only_from_the_autopilot():
    ap = _link()
    ap._on_message(None, _heartbeat(1), 0)
    ap._on_message(None, _from(D.MAVLink_gps_global_origin_message(1, 2, 3, 0), 2, 1), 1)
    assert not ap.origin_known and ap.counters["origin_not_from_autopilot"] == 1
    ap._on_message(None, _from(D.MAVLink_attitude_message(1000, 0.1, 0, 0, 0, 0, 0), 2, 1), 2)
    assert len(ap.attitude) == 0 and ap.counters["attitude_not_from_autopilot"] == 1
    ap._on_message(None, _from(D.MAVLink_gps_global_origin_message(1, 2, 3, 0), 1, 1), 3)
    assert ap.origin_known


def test_an_attitude_stamped_ahead_of_the_autopilots_clock_is_refused():
    clock = Clock()
    ap = _link(clock)
    ap._on_message(None, _heartbeat(1), 0)
    boot_ms = 5_000

    def sample(boot):
        ap._on_message(None, _from(D.MAVLink_attitude_message(boot, 0.1, 0, 0, 0, 0, 0), 1, 1), clock.mono_ns())

    for _ in range(10):
        clock.s += 0.02
        boot_ms += 20
        sample(boot_ms)
    offset_us = ap.attitude.latest_us() - boot_ms * 1000
    sample(boot_ms + 900)  # 0.9 s ahead, arriving with the last real one
    assert ap.counters["attitude_ahead"] == 1
    for _ in range(10):
        clock.s += 0.02
        boot_ms += 20
        sample(boot_ms)
    assert len(ap.attitude) == 20
    # the real samples keep their mapping
    assert abs(ap.attitude.latest_us() - boot_ms * 1000 - offset_us) < 5_000


def _attitude(boot_ms: int, p: float, q: float, r: float) -> SimpleNamespace:
    return SimpleNamespace(
        get_type=lambda: "ATTITUDE", time_boot_ms=boot_ms, roll=0.1, pitch=-0.05, yaw=1.0,
        rollspeed=p, pitchspeed=q, yawspeed=r,
    )  # fmt: skip


def test_attitude_rates_reach_the_cameras_in_body_flu() -> None:
    """A roll right (FRD +p), pitch up (FRD +q) and yaw right (FRD +r) read as FLU (+p, -q, -r), at the
    sample's mapped time, with a covariance no smaller away from the samples; none when the sender left
    the rates at zero."""
    clock = Clock()
    link = AutopilotLink(NodeConfig(entity="d1", system_id=1), 191, clock, clock.mono_ns)
    for k in range(5):
        clock.s += 0.02
        link._on_attitude(_attitude(1000 + 20 * k, 0.3, 0.2, -0.4), clock.mono_ns())
    t_last = link.attitude.latest_us()
    assert t_last is not None
    rate = link.rate_at(t_last - 10_000)
    assert rate is not None
    np.testing.assert_allclose(rate.omega_flu, [0.3, -0.2, 0.4])
    at_sample = link.rate_at(t_last)
    # Between two samples the rate is as well known as the stream predicts itself (a constant stream:
    # the gyro's noise alone), never better than at a sample.
    assert at_sample is not None and np.all(np.diag(rate.cov) >= np.diag(at_sample.cov))
    assert link.rate_at(t_last + 60_000) is None  # the stream stopped
    still = AutopilotLink(NodeConfig(entity="d1", system_id=1), 191, clock, clock.mono_ns)
    still._on_attitude(_attitude(1000, 0.0, 0.0, 0.0), clock.mono_ns())
    assert still.attitude.latest_us() is not None and still.rate_at(still.attitude.latest_us()) is None
    assert math.isfinite(float(np.trace(rate.cov)))


def _fed(clock, *messages):
    """An autopilot link fed 6 rounds, 20 ms apart, of the autopilot's messages, each ``m(time_boot_ms)``."""
    ap = _link(clock)
    ap._on_message(None, _heartbeat(1), 0)
    for k in range(6):
        clock.s += 0.02
        for message in messages:
            ap._on_message(None, _from(message(1000 + 20 * k), 1, 1), clock.mono_ns())
    return ap


def _east(boot):
    """ATTITUDE of a vehicle heading east (yaw 90 deg)."""
    return D.MAVLink_attitude_message(boot, 0, 0, math.pi / 2, 0, 0, 0)


def _heading_east(clock, velocity_message):
    """An autopilot link fed 6 ATTITUDEs of a vehicle heading east (yaw 90 deg), each with the velocity
    message ``velocity_message(time_boot_ms)`` from the autopilot: (the link, the newest velocity's stamp,
    the velocity 10 ms before it)."""
    ap = _fed(clock, _east, velocity_message)
    t = ap.velocities.latest_us()
    assert t is not None
    v = ap.velocity_at(t - 10_000)
    assert v is not None
    return ap, t, v


def test_local_position_velocity_reaches_the_cameras_in_body_flu() -> None:
    """LOCAL_POSITION_NED's velocity (NED) turned into the body's FLU axes by ATTITUDE at the same time: a
    vehicle heading east (yaw 90 deg) flying east at 0.6 m/s and climbing at 0.1 m/s moves along its forward
    and up axes; none from another system (counted), none when the sender left the velocity at zero."""
    clock = Clock()
    ap, t, v = _heading_east(
        clock, lambda boot: D.MAVLink_local_position_ned_message(boot, 1.0, 2.0, -1.0, 0.0, 0.6, -0.1)
    )
    np.testing.assert_allclose(v.velocity_flu, [0.6, 0.0, 0.1], atol=1e-6)
    assert np.all(np.linalg.eigvalsh(v.cov) > 0)
    other = D.MAVLink_local_position_ned_message(2000, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0)
    ap._on_message(None, _from(other, 2, 1), clock.mono_ns())
    assert ap.counters["local_position_not_from_autopilot"] == 1 and ap.velocities.latest_us() == t
    still = D.MAVLink_local_position_ned_message(2000, 1.0, 2.0, -1.0, 0.0, 0.0, 0.0)  # position only
    ap._on_message(None, _from(still, 1, 1), clock.mono_ns())
    assert ap.velocities.latest_us() == t


def _odometry(time_usec, child, v, yaw=math.pi / 2, estimator=8):
    """PX4's ODOMETRY (its estimator's, in LOCAL_NED) with its attitude a heading of ``yaw``."""
    q = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    nan21 = [math.nan] * 21
    return D.MAVLink_odometry_message(time_usec, 1, child, 1.0, 2.0, -1.0, q, *v, 0.0, 0.0, 0.0, nan21, nan21, 0,
                                      estimator)  # fmt: skip


def test_odometry_velocity_reaches_the_cameras_when_the_autopilot_streams_no_local_position() -> None:
    """A PX4 that streams ODOMETRY and no LOCAL_POSITION_NED: its velocity in BODY_FRD (or LOCAL_NED) turned
    into the body's FLU axes by ATTITUDE, as LOCAL_POSITION_NED's is; PX4's loopback of our own vision
    refused (counted); none from another system (counted); while LOCAL_POSITION_NED's velocity comes, it
    alone is used."""
    for child, v in ((12, (0.6, 0.0, -0.1)), (1, (0.0, 0.6, -0.1))):  # heading east, flying east, climbing
        clock = Clock()
        ap, t, got = _heading_east(clock, lambda boot, child=child, v=v: _odometry(boot * 1000, child, v))
        np.testing.assert_allclose(got.velocity_flu, [0.6, 0.0, 0.1], atol=1e-6)
    clock.s += 0.02
    ap._on_message(None, _from(_odometry(1200_000, 12, (0.0, 0.5, 0.0), estimator=2), 1, 1), clock.mono_ns())
    assert ap.counters["odometry_velocity_rejected"] == 1 and ap.velocities.latest_us() == t
    ap._on_message(None, _from(_odometry(1200_000, 12, (0.0, 0.5, 0.0)), 2, 1), clock.mono_ns())
    assert ap.counters["odometry_not_from_autopilot"] == 1 and ap.velocities.latest_us() == t

    both = _fed(
        Clock(),
        _east,
        lambda boot: D.MAVLink_local_position_ned_message(boot, 1.0, 2.0, -1.0, 0.0, 0.6, -0.1),
        lambda boot: _odometry(boot * 1000 + 10_000, 1, (0.0, 0.3, 0.0)),  # another estimate, between them
    )
    t = both.velocities.latest_us()
    assert t is not None
    for dt in (0, 10_000, 30_000):
        got = both.velocity_at(t - dt)
        assert got is not None
        np.testing.assert_allclose(got.velocity_flu, [0.6, 0.0, 0.1], atol=1e-6)


def test_attitude_after_its_newest_sample_is_turned_on_by_the_rate_sent_with_it() -> None:
    """ATTITUDE's body rates (FRD) go into the history with its attitude: after the newest sample the
    attitude is that sample turned on by its rate (yawing right at 0.5 rad/s: FLU yaw falls)."""
    ap = _fed(Clock(), lambda boot: D.MAVLink_attitude_message(boot, 0, 0, 0.0005 * (boot - 1000), 0, 0, 0.5))
    t = ap.attitude.latest_us()
    assert t is not None
    R_now, R_later = ap.attitude_at(t), ap.attitude_at(t + 10_000)
    assert R_now is not None and R_later is not None
    turned = (R_now.inv() * R_later).as_rotvec()
    np.testing.assert_allclose(turned, [0.0, 0.0, -0.5 * 0.01], atol=1e-12)
