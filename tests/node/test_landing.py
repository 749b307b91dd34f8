"""The node's landing output: what goes out after each evaluation, and what never does."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import LandingConfig, parse_world
from atlas_onboard.core.graph import EntityPose, GraphResult
from atlas_onboard.node.landing import LandingOutput

WORLD = parse_world(
    {
        "conventions": {"world": "ENU", "body": "FRD"},
        "entities": {
            "world": {"markers": [{"id": 1, "size_m": 0.2, "pose": {"pos": [2.0, 1.0, 0.0]}}]},
            "drone": {"markers": [{"id": 5, "size_m": 0.1, "pose": {"pos": [0, 0, -0.05]}}]},
            "rover": {"markers": [{"id": 7, "size_m": 0.2, "pose": {"pos": [0.1, 0, -0.3]}}]},
        },
    }
)


def pose(name, p, t_us, sigma=0.005, yaw_deg=0.0):
    cov = np.diag([sigma**2] * 3 + [1e-6] * 3)
    q = Rotation.from_euler("z", yaw_deg, degrees=True).as_quat()
    return EntityPose(name, np.asarray(p, float), q, 1, 1, 1, sigma, t_us, covariance=cov)


def result(*poses):
    return GraphResult({p.name: p for p in poses}, tuple(p.name for p in poses), {}, (), 1)


def output(**kw):
    sent = []
    cfg = LandingConfig(**{"target": "world", "autopilot": "ardupilot", "marker": 1, **kw})
    return LandingOutput(cfg, "drone", WORLD, sent.append), sent


def test_world_pad_marker_in_ardupilot_form():
    out, sent = output()
    now = 10_000_000
    d = out.update(result(pose("drone", [2.0, 1.5, 1.0], now - 40_000)), 0, now)
    # The marker at ENU (2, 1, 0), the drone at (2, 1.5, 1) nose east: 0.5 m to its right, 1 m below.
    assert d.verdict.value == "send" and len(sent) == 1
    assert (sent[0]["frame"], sent[0]["time_usec"]) == (12, now - 40_000)
    assert (sent[0]["x"], sent[0]["y"], sent[0]["z"]) == pytest.approx((0.0, 0.5, 1.0))


def test_rate_no_repeats_and_never_stale():
    out, sent = output(rate_hz=10.0, max_age_s=0.3)
    t0 = 10_000_000
    out.update(result(pose("drone", [2, 1, 1], t0)), 0, t0)
    out.update(result(pose("drone", [2, 1, 1], t0 + 30_000)), 50_000_000, t0 + 50_000)  # within 0.1 s: not due
    out.update(result(pose("drone", [2, 1, 1], t0)), 200_000_000, t0 + 200_000)  # no newer observation
    out.update(result(pose("drone", [2, 1, 1], t0 + 100_000)), 400_000_000, t0 + 401_000)  # 0.301 s old
    assert [f["time_usec"] for f in sent] == [t0]
    assert out.counts["repeat"] == 1 and out.counts["stale"] == 1
    out.update(result(pose("drone", [2, 1, 1], t0 + 500_000)), 600_000_000, t0 + 600_000)
    assert [f["time_usec"] for f in sent] == [t0, t0 + 500_000]


def test_rover_point_in_px4_form():
    # FRD world file: the rover's marker 0.3 m above its origin (z -0.3 FRD), 0.1 m ahead. The rover at
    # ENU (4, 0, 0) facing north: the marker at ENU (4, 0.1, 0.3), NED (0.1, 4, -0.3).
    out, sent = output(target="rover", marker=7, autopilot="px4")
    now = 5_000_000
    out.update(result(pose("drone", [4, 0, 1.5], now), pose("rover", [4, 0, 0], now - 100_000, yaw_deg=90)), 0, now)
    assert sent[0]["frame"] == 1 and sent[0]["time_usec"] == now - 100_000
    assert (sent[0]["x"], sent[0]["y"], sent[0]["z"]) == pytest.approx((0.1, 4.0, -0.3))
    out2, sent2 = output(target="rover", marker=7, autopilot="px4", max_sigma_m=0.01)
    out2.update(result(pose("drone", [4, 0, 1.5], now), pose("rover", [4, 0, 0], now, sigma=0.02)), 0, now)
    assert sent2 == [] and out2.counts["uncertain"] == 1


def test_the_filters_velocity_widens_an_old_moving_target():
    # A rover driving at 1 m/s under a ceiling camera, with the EKF: a decision 0.1 s after the last
    # image counts the 0.1 m the rover may have moved since (sigma sqrt(s^2 + 0.1^2) > 0.05 m); without
    # the filter's velocity the same pose goes out.
    from atlas_onboard.core.ekfbank import EkfBank
    from atlas_onboard.listener import Listener
    from atlas_onboard.node.output import make_ekf
    from atlas_onboard.node.setup import make_graph
    from tests.helpers import observe
    from tests.helpers import pose as true_pose

    world = parse_world(
        {
            "fusion": {"filter": "ekf"},
            "entities": {
                "world": {
                    "sensors": [{"name": "ceiling", "id": 10, "pose": {"pos": [0, 0, 4], "rpy_deg": [0, 90, 0]}}]
                },
                "drone": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
                "rover": {"markers": [{"id": 7, "size_m": 0.2, "pose": {"pos": [0, 0, 0.3]}}]},
            },
        }
    )
    graph = make_graph(world, "drone")
    listener = Listener(world, graph)
    ekf = make_ekf(world)
    assert isinstance(ekf, EkfBank)
    cfg = LandingConfig(target="rover", autopilot="px4", marker=7)
    with_filter, plain = LandingOutput(cfg, "drone", world, [].append), LandingOutput(cfg, "drone", world, [].append)
    t0 = 10_000_000
    for k in range(30):
        t_us = t0 + k * 33_333
        truth = {"world": RigidTransform.identity(), "drone": true_pose([0.0, 0.0, 1.5], [0, 0, 0]),
                 "rover": true_pose([k * 0.0333, 0.2, 0.0], [0, 0, 0])}  # fmt: skip
        for marker in (5, 7):
            listener.accept(observe(world, truth, 10, marker, sigma_m=0.003, capture_time_us=t_us), t_us * 1000)
        result = graph.evaluate(t_us * 1000)
        with_filter.update(result, t_us * 1000, t_us, ekf)  # as the node: after every evaluation
        ekf.update(result, t_us, only="drone")
    late = t_us + 100_000
    d_filter = with_filter.update(result, late * 1000, late, ekf)
    d_plain = plain.update(result, 0, late)
    assert d_plain.verdict.value == "send" and d_plain.sigma_m < 0.05
    assert d_filter.verdict.value == "uncertain"
    assert d_filter.sigma_m == pytest.approx(math.hypot(d_plain.sigma_m, 0.1), rel=0.15)
