"""The EKF option (fusion.filter: ekf) from graph candidates to the autopilot: it predicts through
short gaps against ground truth, stops after ekf_max_predict_s, estimates velocity, and one
injected wrong observation (a flipped pose, a wrong id) cannot move the pose beyond the gate."""

import threading
import time

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import AutopilotConfig, LinkConfig, NodeConfig, parse_world
from atlas_onboard.core.ekf import EkfSettings
from atlas_onboard.core.ekfbank import EkfBank
from atlas_onboard.core.graph import TransformGraph
from atlas_onboard.node.loop import Node
from tests.helpers import observe, pose
from tests.node.test_loop import FakeTransport

MS = 1_000_000
V = np.array([1.0, 0.5, 0.0])  # the drone's constant velocity, m/s


def truth_at(t_s):
    return pose(list(np.array([0.5, -0.3, 1.2]) + V * t_s), [0, 0, 30])


def test_bank_predicts_through_a_gap_and_lapses_after_the_horizon():
    rng = np.random.default_rng(3)
    g = TransformGraph(["world", "d"], 250 * MS, keep_candidates=True)
    bank = EkfBank(EkfSettings(accel_noise=2.0, max_gap_s=0.5), max_predict_s=0.5)
    t0_us = 1_700_000_000_000_000
    for k in range(60):  # 2 s of 30 Hz detections, 1 cm noise
        t = k / 30
        T = truth_at(t).inv()
        p = T.translation + rng.normal(size=3) * 0.01
        g.update_edge((1, 0), "d", "world", p, T.rotation.as_quat(), 0.01, int(t * 1e9), t0_us + int(t * 1e6))
        bank.update(g.evaluate(int(t * 1e9)), t0_us + int(t * 1e6))
    last_t = 59 / 30
    est = bank.pose("d", t0_us + int((last_t + 0.02) * 1e6))
    # The velocity within 3 sigma of the filter's own velocity covariance (with ekf_accel_noise 2 m/s^2
    # and 1 cm detections at 30 Hz, sigma is about 0.4 m/s).
    v_sigma = np.sqrt(np.diag(est.velocity_covariance)[:3])
    assert np.all(v_sigma < 0.5), v_sigma
    assert np.all(np.abs(est.velocity_m_s - V) < 3 * v_sigma), (est.velocity_m_s, v_sigma)
    # 0.3 s into a gap (no detection): predicted by the constant-velocity model.
    in_gap = bank.pose("d", t0_us + int((last_t + 0.3) * 1e6))
    assert in_gap.capture_time_us > est.capture_time_us
    t_gap = (in_gap.capture_time_us - t0_us) / 1e6
    err = np.linalg.norm(in_gap.p_world_m - truth_at(t_gap).translation)
    held = np.linalg.norm(est.p_world_m - truth_at(t_gap).translation)  # the pose without prediction
    assert err < 0.1 and err < held / 3, (err, held)
    # Its covariance grew with the prediction and covers the error (3 sigma).
    assert in_gap.covariance[0, 0] > est.covariance[0, 0]
    assert err < 3 * np.sqrt(np.trace(in_gap.covariance[:3, :3])), (err, np.diag(in_gap.covariance))
    # Past the horizon the pose is lost, as without a filter.
    assert bank.pose("d", t0_us + int((last_t + 0.6) * 1e6)) is None


WORLD = parse_world(
    {
        # The graph's outlier gate (on by default) off: these tests are about the EKF's own gating.
        "fusion": {"filter": "ekf", "ekf_max_predict_s": 0.5, "outlier_gate_sigma": 0},
        "entities": {
            "world": {
                "markers": [
                    {"id": 0, "size_m": 0.2, "pose": {"pos": [0, 0, 0]}},
                    {"id": 1, "size_m": 0.2, "pose": {"pos": [1, 0, 0]}},
                ]
            },
            "d1": {"sensors": [{"name": "down", "id": 1, "pose": {"pos": [0, 0, 0], "rpy_deg": [0, 90, 0]}}]},
        },
    }
)


def run_node(feed):
    cfg = NodeConfig(entity="d1", system_id=7, autopilot=AutopilotConfig(LinkConfig("udpout:127.0.0.1:9")))
    transport = FakeTransport(time.monotonic_ns)
    node = Node(WORLD, cfg, transport)
    thread = threading.Thread(target=node.run)
    thread.start()
    transport.started.wait(5)
    try:
        feed(node)
    finally:
        node.stop()
        thread.join(5)
    return node, transport


def moving_feed(node, t_start, duration_s, corrupt=None, at=20):
    """Observations of marker 0 at 30 Hz of the drone moving at V, captured now on the wall clock;
    the ``at``-th one replaced by ``corrupt(md)``."""
    n = int(duration_s * 30)
    for k in range(n):
        now_us = time.time_ns() // 1000
        t = now_us / 1e6 - t_start
        truth = {"world": RigidTransform.identity(), "d1": truth_at(t)}
        md = observe(WORLD, truth, 1, 0, sigma_m=0.005, capture_time_us=now_us)
        if corrupt is not None and k == at:
            md = corrupt(md)
        node.deliver_local([md])
        time.sleep(1 / 30)


def errors(transport, t_start):
    out = []
    for _, ap in transport.autopilot:
        t = ap.pose.capture_time_us / 1e6 - t_start
        out.append((t, np.linalg.norm(ap.pose.p_world_m - truth_at(t).translation)))
    return np.array(out)


def test_node_with_ekf_predicts_through_a_gap_then_loses_the_pose():
    t_start = time.time()

    def feed(node):
        moving_feed(node, t_start, 1.0)
        time.sleep(0.3)  # a 0.3 s gap: the filter keeps the pose going
        moving_feed(node, t_start, 0.3)
        time.sleep(0.9)  # longer than ekf_max_predict_s: the pose is lost

    node, tr = run_node(feed)
    e = errors(tr, t_start)
    assert len(e) > 30
    steady = e[e[:, 0] > 0.3]
    assert np.percentile(steady[:, 1], 95) < 0.03, steady[:, 1].max()
    # Messages kept coming during the first gap (1.0-1.3 s), at about the autopilot rate.
    gap_msgs = e[(e[:, 0] > 1.08) & (e[:, 0] < 1.25)]
    assert len(gap_msgs) >= 3 and gap_msgs[:, 1].max() < 0.05
    # Every message carries the filter's velocity.
    v = np.array([ap.pose.velocity_m_s for _, ap in tr.autopilot[-10:]])
    np.testing.assert_allclose(v.mean(axis=0), V, atol=0.2)
    texts = [t for _, t in tr.status]
    assert texts[0] == "atlas d1: pose found" and texts[-1] == "atlas d1: pose lost"
    assert texts.count("atlas d1: pose lost") == 1  # the short gap did not lose it
    assert node.counters()["ekf_accepted"] > 30


def test_one_flipped_observation_does_not_move_the_pose():
    t_start = time.time()

    def flipped(md):
        # The planar ambiguity's other solution: the tag tilted 40 degrees and shifted 30 cm.
        T = RigidTransform.from_components(md.p_sensor_marker_m, Rotation.from_quat(md.q_sensor_marker_xyzw()))
        T = T * pose([0.3, 0.0, 0.0], [0, 40, 0])
        x, y, z, w = T.rotation.as_quat()
        return type(md)(md.sensor_id, md.marker_id, md.sigma_m, tuple(T.translation), (w, x, y, z), md.capture_time_us)

    def wrong_id(md):
        # Marker 1's detection reported as marker 0: a 1 m jump if believed.
        T = pose(list(md.p_sensor_marker_m)) * pose([1.0, 0.0, 0.0])
        return type(md)(md.sensor_id, md.marker_id, md.sigma_m, tuple(T.translation), md.q_sensor_marker_wxyz,
                        md.capture_time_us)  # fmt: skip

    for bad in (flipped, wrong_id):
        node, tr = run_node(lambda node, bad=bad: moving_feed(node, t_start, 1.0, corrupt=bad))
        e = errors(tr, t_start)
        assert len(e) > 15
        assert e[:, 1].max() < 0.05, (bad.__name__, e[:, 1].max())
        assert node.counters().get("ekf_gated", 0) == 1, node.counters()
