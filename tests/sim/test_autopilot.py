"""The simulated autopilot's ATTITUDE carries the body's angular rates (FRD, as the autopilots send them),
and the node's autopilot link keeps them with each attitude sample in the body's FLU axes; its
LOCAL_POSITION_NED carries its EKF's velocity, which the node turns into the body's axes."""

import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.config import AutopilotConfig, LinkConfig, NodeConfig
from atlas_onboard.mavlink.transport import MavlinkTransport
from atlas_onboard.sim.autopilot import SimAutopilot
from atlas_onboard.sim.ekf_velocity import EkfVelocityNoise
from atlas_onboard.sim.gyro import GyroNoise
from tests.e2e.helpers import wait_for
from tests.helpers import world_from

pytestmark = pytest.mark.deadlines  # the simulated autopilot's threads and sockets, in real time

RATE_FLU = np.array([0.3, -0.2, 0.5])  # rad/s: roll right... about the body's forward, left and up axes


def _stream(rates, gyro: GyroNoise, seconds: float = 1.5):
    """A transport fed ATTITUDE at 50 Hz for ``seconds`` by a simulated autopilot whose body turns at
    ``rates`` (None: an autopilot that sends zero rates); returns the node's rate at 60 times of the last
    second, each beside the wall time it was asked for."""
    sim = SimAutopilot(
        system_id=1, attitude=lambda _t: Rotation.identity(), attitude_hz=50.0, rates=rates, gyro=gyro
    ).start()
    world = world_from({"entities": {"d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0]}}]}}})
    config = NodeConfig(entity="d1", system_id=1, autopilot=AutopilotConfig(LinkConfig(f"udpout:127.0.0.1:{sim.port}")))
    transport = MavlinkTransport(world, config)
    transport.start(lambda items: None)
    try:
        transport.tick(0)  # a heartbeat: the simulated autopilot learns where the node is
        assert wait_for(lambda: sim._peer is not None)
        assert wait_for(lambda: len(transport.attitude) >= int(seconds * 50), 10)
        time.sleep(0.2)
        last = transport.attitude.latest_us()
        assert last is not None
        times = np.linspace(last - 1_000_000, last, 60).astype(int)
        return [None if (r := transport.rate_at(int(t))) is None else r.omega_flu for t in times]
    finally:
        transport.close()
        sim.stop()


def test_attitude_carries_the_true_rates_in_the_body_axes():
    got = _stream(lambda _t: RATE_FLU, GyroNoise(density=0.0, bias_sigma=0.0))
    assert all(w is not None for w in got)
    np.testing.assert_allclose(np.array(got), np.tile(RATE_FLU, (len(got), 1)), atol=1e-6)  # float32 on the wire


def test_noisy_rates_average_to_the_truth_within_the_gyros_bias():
    noise = GyroNoise()
    got = np.array(_stream(lambda _t: RATE_FLU, noise))
    # 60 look-ups over a second interpolate ~50 samples: their mean is the truth plus the bias (4 sigma)
    # plus the white noise averaged over the samples (4 sigma of 50 samples' mean).
    bound = 4.0 * noise.bias_sigma + 4.0 * noise.density * np.sqrt(50.0) / np.sqrt(50.0)
    assert np.all(np.abs(got.mean(axis=0) - RATE_FLU) < bound)
    assert got.std(axis=0).max() > 0.0  # noise there is


@pytest.mark.parametrize("rates", [None])
def test_an_autopilot_without_rates_gives_none(rates):
    assert all(w is None for w in _stream(rates, GyroNoise()))


R_WORLD_BODY = Rotation.from_euler("ZYX", [50.0, 4.0, -3.0], degrees=True)  # ENU / FLU
V_WORLD = np.array([0.6, 0.2, -0.1])  # m/s, ENU


def _velocities(noise: EkfVelocityNoise) -> list:
    """The node's body velocity at 30 times of the last half second of a simulated autopilot streaming
    ATTITUDE (its heading offset, no attitude noise) and LOCAL_POSITION_NED at 30 Hz."""
    sim = SimAutopilot(
        system_id=1, attitude=lambda _t: R_WORLD_BODY, attitude_hz=50.0, attitude_noise_deg=0.0,
        attitude_bias_deg=0.0, velocity=lambda _t: V_WORLD, ekf_velocity=noise, local_position_hz=30.0,
    ).start()  # fmt: skip
    world = world_from({"entities": {"d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0]}}]}}})
    config = NodeConfig(entity="d1", system_id=1, autopilot=AutopilotConfig(LinkConfig(f"udpout:127.0.0.1:{sim.port}")))
    transport = MavlinkTransport(world, config)
    transport.start(lambda items: None)
    try:
        transport.tick(0)
        assert wait_for(lambda: sim._peer is not None)
        link = transport.autopilot_link
        assert wait_for(lambda: len(link.velocities._samples) >= 30, 10)
        last = link.velocities.latest_us()
        assert last is not None
        times = np.linspace(last - 500_000, last, 30).astype(int)
        return [transport.velocity_at(int(t)) for t in times]
    finally:
        transport.close()
        sim.stop()


def test_local_position_carries_the_velocity_that_the_node_reads_in_the_body_axes():
    got = _velocities(EkfVelocityNoise(sigma_m_s=0.0, accel_bias_sigma=0.0))
    assert all(v is not None for v in got)
    truth = R_WORLD_BODY.inv().apply(V_WORLD)  # the autopilot's heading offset cancels: its frame, its attitude
    np.testing.assert_allclose(np.array([v.velocity_flu for v in got]), np.tile(truth, (len(got), 1)), atol=1e-5)


def test_the_ekf_velocity_is_not_the_truth():
    got = _velocities(EkfVelocityNoise())
    truth = R_WORLD_BODY.inv().apply(V_WORLD)
    err = np.array([v.velocity_flu for v in got]) - truth
    assert np.abs(err).max() > 1e-4  # noise there is
    assert np.all(np.abs(err) < 4 * np.sqrt(np.array([np.diag(v.cov) for v in got])))  # within the node's sigma
