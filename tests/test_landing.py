"""The node's landing output: what goes out after each evaluation, and what never does."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.config import LandingConfig, parse_world
from atlas_onboard.core.graph import EntityPose, GraphResult
from atlas_onboard.landing import LandingOutput

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
