"""Naming a frame mistake from the gravity direction: each mistake planted in a world file (loaded by
the real loader) gives the vision attitude the candidate's rotation, and is diagnosed as itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.config import parse_world
from atlas_onboard.core import frames, mounting
from atlas_onboard.sim.bench import bench_world_doc

AXES = {"down": np.array([0.0, 0.0, 1.0])}  # the bench camera looks down: FRD +z


def _loaded(mistake: str | None):
    doc = bench_world_doc(Path("/nonexistent"), 14550, mistake)
    doc.pop("nodes")
    doc["entities"]["drone"]["sensors"][0].pop("camera")
    return parse_world(doc)


def _vision_attitude(R_true_ned_frd: Rotation, mistake: str | None) -> Rotation:
    """The attitude the node computes from a camera that sees the world as it is, through the world
    file with ``mistake``: R_world_body = R_world_marker R_marker_cam R_cam_body (file's values)."""
    true, bad = _loaded(None), _loaded(mistake)
    R_true_enu_flu = frames.R_ENU_NED * R_true_ned_frd * frames.R_FLU_FRD.inv()
    sensor_t, sensor_b = true.sensors[1], bad.sensors[1]
    marker_t, marker_b = true.markers[3], bad.markers[3]
    R_world_cam = R_true_enu_flu * sensor_t.T_entity_sensor.rotation
    R_marker_cam = marker_t.T_entity_marker.rotation.inv() * R_world_cam  # what the camera measures
    R_vis_enu_flu = marker_b.T_entity_marker.rotation * R_marker_cam * sensor_b.T_entity_sensor.rotation.inv()
    return frames.R_ENU_NED.inv() * R_vis_enu_flu * frames.R_FLU_FRD


EXPECTED = {
    "mount90": "the world file turns camera down +90 deg about its optical axis",
    "flu_as_frd": "body axes written in FLU but declared FRD",
    "ned_as_enu": "world file written in NED but declared ENU",
    None: "correct",
}


def _names(d: mounting.Diagnosis, within_deg: float) -> set[str]:
    return {c.name for c, err in d.ranked if err <= within_deg}


@settings(max_examples=60, deadline=None)
@given(
    yaw=st.floats(-180, 180),
    tilt=st.floats(0.0, 25.0),
    tilt_dir=st.floats(0, 360),
    mistake=st.sampled_from(list(EXPECTED)),
)
def test_the_planted_mistake_explains_the_attitudes_and_far_ones_do_not(
    yaw: float, tilt: float, tilt_dir: float, mistake: str | None
) -> None:
    axis = np.array([np.cos(np.radians(tilt_dir)), np.sin(np.radians(tilt_dir)), 0.0])
    R_ap = Rotation.from_euler("z", yaw, degrees=True) * Rotation.from_rotvec(np.radians(tilt) * axis)
    noise = Rotation.from_rotvec(np.random.default_rng(0).normal(0, np.radians(0.5), (30, 3)))
    R_vis = _vision_attitude(R_ap, mistake)
    cands = mounting.candidates(AXES)
    d = mounting.diagnose(noise * R_ap, Rotation.concatenate([R_vis] * 30), cands)
    planted = next(c for c in cands if c.name.startswith(EXPECTED[mistake]))
    assert planted.name in _names(d, mounting.AGREE_DEG)
    # A candidate whose gravity (noise-free) lies over twice the tolerance from the planted one's is not
    # taken for it.
    u = mounting.up_vectors(R_ap)
    for c, err in d.ranked:
        gap = mounting._angles_deg(mounting._predict(c, u), mounting._predict(planted, u))[0]
        if gap > 2 * mounting.AGREE_DEG + 1.0:
            assert err > mounting.AGREE_DEG, (c.name, gap, err)


@pytest.mark.parametrize("mistake", list(EXPECTED))
def test_on_the_tilted_bench_each_mistake_is_the_only_explanation(mistake: str | None) -> None:
    from atlas_onboard.sim.bench import BENCH_RPY_DEG

    R_enu_flu = Rotation.from_euler("ZYX", BENCH_RPY_DEG[::-1], degrees=True)
    R_ap = frames.R_ENU_NED.inv() * R_enu_flu * frames.R_FLU_FRD
    d = mounting.diagnose(R_ap, _vision_attitude(R_ap, mistake), mounting.candidates(AXES))
    assert d.best.name.startswith(EXPECTED[mistake])
    assert _names(d, mounting.AGREE_DEG) == {d.best.name} and not d.hidden


def test_level_bench_reports_turns_about_a_vertical_axis_as_not_seen() -> None:
    R = Rotation.from_euler("z", 30, degrees=True)
    d = mounting.diagnose(R, _vision_attitude(R, "mount90"), mounting.candidates(AXES))
    assert {c.name.split(" about")[0] for c in d.hidden} == {
        f"the world file turns camera down {a} deg" for a in ("+90", "-90", "+180")
    }
    assert d.ranked[0][1] < mounting.AGREE_DEG  # indistinguishable from correct: not called a failure


@pytest.mark.parametrize("deg", [90.0, -90.0, 180.0])
def test_the_angle_named_is_the_one_planted(deg: float) -> None:
    true = _loaded(None)
    R_opt_true = true.sensors[1].T_entity_sensor.rotation
    axis_flu = R_opt_true.apply([0.0, 0.0, 1.0])
    R_file = Rotation.from_rotvec(np.radians(deg) * axis_flu) * R_opt_true  # the file's camera turned by deg
    D_flu = R_opt_true * R_file.inv()
    D_frd = frames.R_FLU_FRD.inv() * D_flu * frames.R_FLU_FRD
    prefix = f"the world file turns camera down {deg:+.0f}"
    named = next(c for c in mounting.candidates(AXES) if c.name.startswith(prefix))
    assert (named.D_body.inv() * D_frd).magnitude() < 1e-9


def test_yaw_difference_is_circular() -> None:
    a = Rotation.from_euler("z", [[179.0], [-179.0]], degrees=True)
    b = Rotation.from_euler("z", [[-179.0], [179.0]], degrees=True)
    assert mounting.yaw_difference_deg(a, b) == pytest.approx(0.0, abs=1e-9)
    assert mounting.yaw_difference_deg(a[:1], b[:1]) == pytest.approx(2.0)
