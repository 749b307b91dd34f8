"""End to end over 127.0.0.1: a real node process sends LANDING_TARGET to the simulated autopilot, in the
form each autopilot takes, for a rover that only a ceiling camera (the test's peer) sees."""

import math
import time

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform

from atlas_onboard.sim.lander import Lander, LanderSettings
from tests.e2e.helpers import start_node_with_peer, wait_for
from tests.helpers import observe, pose

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group


def world_doc(peer_port, ap_port, form):
    return {
        "fusion": {"age_sigma_m_per_s": 0, "age_sigma_deg_per_s": 0},
        "entities": {
            "world": {"sensors": [{"name": "ceiling", "id": 10, "pose": {"pos": [0, 0, 4], "rpy_deg": [0, 90, 0]}}]},
            "d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
            "rover": {"markers": [{"id": 7, "size_m": 0.2, "pose": {"pos": [0.1, 0, 0.3]}}]},
        },
        "nodes": {
            "d1": {
                "system_id": 1,
                "autopilot": {"url": f"udpout:127.0.0.1:{ap_port}"},
                "peers": [f"udpin:127.0.0.1:{peer_port}"],
                "landing": {"target": "rover", "marker": 7, "autopilot": form, "max_sigma_m": 0.2},
            },
            "world": {"system_id": 250},
        },
    }


# The drone at ENU (1, 2, 1.5) nose north; the rover at ENU (1.2, 2.5, 0) facing east, its deck tag
# 0.1 m ahead and 0.3 m up: ENU (1.3, 2.5, 0.3) = NED (2.5, 1.3, -0.3). From the drone (FRD, nose
# north): 0.5 m forward, 0.3 m right, 1.2 m down.
TRUTH = {"world": RigidTransform.identity(), "d1": pose([1.0, 2.0, 1.5], [0, 0, 90]), "rover": pose([1.2, 2.5, 0.0])}


@pytest.mark.parametrize("form", ["px4", "ardupilot"])
def test_landing_target_in_each_autopilots_form(tmp_path, form):
    world, ap, node, peer = start_node_with_peer(tmp_path, lambda port, ap_port: world_doc(port, ap_port, form))
    # The autopilot flies on what it gets (sim/lander.py), at the drone's true pose and heading.
    ap.lander = Lander(LanderSettings(form), np.array([1.0, 2.0, 1.5]), yaw_rad=math.pi / 2)
    try:
        t0 = int(time.time() * 1e6)
        stamps = []
        for k in range(15):
            stamp = t0 + k * 33_000
            stamps.append(stamp)
            for marker in (5, 7):
                peer.send(observe(world, TRUTH, 10, marker, sigma_m=0.01, capture_time_us=stamp), world.fingerprint())
            time.sleep(0.033)
        assert wait_for(lambda: len(ap.landing_targets) >= 3, timeout=10.0), node.log()
        time.sleep(0.5)  # nothing new is observed from here on
        got = [f for _, f in ap.landing_targets]
        # Each message is for one of the observations sent, each at most once (never a repeat).
        times = [f["time_usec"] for f in got]
        assert set(times) <= set(stamps) and len(set(times)) == len(times)
        for f in got:
            assert f["position_valid"] == 1
            if form == "px4":
                assert f["frame"] == 1  # MAV_FRAME_LOCAL_NED
                assert (f["x"], f["y"], f["z"]) == pytest.approx((2.5, 1.3, -0.3), abs=1e-3)
                # The deck tag's FRD x (the rover's nose, east): yaw 90 deg in NED.
                assert np.abs(f["q"]) == pytest.approx([math.sqrt(0.5), 0, 0, math.sqrt(0.5)], abs=1e-3)
            else:
                assert f["frame"] == 12  # MAV_FRAME_BODY_FRD
                assert (f["x"], f["y"], f["z"]) == pytest.approx((0.5, 0.3, 1.2), abs=1e-3)
                assert f["distance"] == pytest.approx(math.sqrt(0.25 + 0.09 + 1.44), abs=1e-3)
                assert (f["angle_x"], f["angle_y"]) == pytest.approx((math.atan(0.3 / 1.2), math.atan(-0.5 / 1.2)),
                                                                     abs=1e-3)  # fmt: skip
        # The autopilot's own estimate of the target: the deck tag, ENU (1.3, 2.5, 0.3); it is on its way.
        assert ap.lander.target_m == pytest.approx((1.3, 2.5, 0.3), abs=0.01) and ap.lander.refused == 0
        assert ap.lander.phase.value in ("approach", "descend")
    finally:
        peer.close()
        node.stop()
        ap.stop()
