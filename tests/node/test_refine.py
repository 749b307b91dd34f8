"""Live refinement's shell: the listener's refined marker poses (and their covariance in eq. 1), the
node's grouping of observations by image, the refined world file, and the ``refine`` settings."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.config import ConfigError, RefineConfig, load_node, load_world
from atlas_onboard.core import covariance
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.errors import AtlasError
from atlas_onboard.listener import Listener
from atlas_onboard.node.refine import LiveRefinement
from atlas_onboard.node.setup import make_graph
from tests.config.common import NODES
from tests.helpers import observe, pose, world_from

DOC = {
    "fusion": {"age_sigma_m_per_s": 0},
    "entities": {
        "world": {
            "markers": [
                {"id": 0, "size_m": 0.2, "pose": {"pos": [0, 0, 0]}},
                {"id": 1, "size_m": 0.2, "pose": {"pos": [0.6, 0, 0], "rpy_deg": [0, 0, 30]}},
                {"id": 2, "size_m": 0.2, "pose": {"pos": [0, 0.6, 0], "rpy_deg": [0, 0, -20]}},
            ]
        },
        "drone": {"sensors": [{"name": "cam", "id": 1, "pose": {"pos": [0, 0, 0], "rpy_deg": [0, 90, 0]}}]},
    },
}
TRUTH = {"world": pose([0, 0, 0]), "drone": pose([0.3, 0.3, 1.5], [5, 3, 40])}


def _edge(listener: Listener, md: MarkerData):
    return listener.edge_from(md)


def test_a_refined_marker_pose_is_used_in_eq1_with_its_covariance():
    world = world_from(DOC)
    listener = Listener(world, make_graph(world))
    md = observe(world, TRUTH, 1, 1)
    # The marker placed elsewhere: the edge is what a world file with it there gives.
    T_new = pose([0.62, -0.01, 0.005], [0.5, -0.3, 31])
    moved_doc = {**DOC, "entities": {**DOC["entities"], "world": {"markers": [
        *DOC["entities"]["world"]["markers"][:1],
        {"id": 1, "size_m": 0.2, "pose": {"pos": T_new.translation.tolist(),
                                          "rot": dict(zip("xyzw", T_new.rotation.as_quat().tolist(), strict=True))}},
        *DOC["entities"]["world"]["markers"][2:],
    ]}}}  # fmt: skip
    moved_world = world_from(moved_doc)
    expected = _edge(Listener(moved_world, make_graph(moved_world)), md)
    listener.set_marker_pose(1, T_new.as_matrix(), np.zeros((6, 6)))
    got = _edge(listener, md)
    np.testing.assert_allclose(got.p_a_b, expected.p_a_b, atol=1e-12)
    np.testing.assert_allclose(got.cov_a_b, expected.cov_a_b, atol=1e-15)
    np.testing.assert_allclose(listener.marker_pose(1), T_new.as_matrix(), atol=1e-12)
    # With a covariance, the edge's grows by it carried through eq. 1 (checked by finite differences).
    C = np.diag([1e-6, 4e-6, 9e-6, 1e-5, 2e-5, 3e-5])
    listener.set_marker_pose(1, T_new.as_matrix(), C)
    added = _edge(listener, md).cov_a_b - expected.cov_a_b
    J = np.zeros((6, 6))
    h = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        M = T_new.as_matrix().copy()
        M[:3, 3] += d[:3]  # dp in the world frame, dtheta about the marker's own axes
        M[:3, :3] = M[:3, :3] @ Rotation.from_rotvec(d[3:]).as_matrix()
        probe = Listener(world, make_graph(world))
        probe.set_marker_pose(1, M, np.zeros((6, 6)))
        e = _edge(probe, md)
        J[:3, k] = (e.p_a_b - got.p_a_b) / h
        R0 = Rotation.from_quat(got.q_a_b_xyzw)
        J[3:, k] = (R0.inv() * Rotation.from_quat(e.q_a_b_xyzw)).as_rotvec() / h
    np.testing.assert_allclose(added, covariance.transform(J, C), rtol=1e-4, atol=1e-12)


def _image(world, mids, stamp_us, ambiguity=0.0):
    mds = [replace(observe(world, TRUTH, 1, m, capture_time_us=stamp_us), ambiguity_ratio=ambiguity) for m in mids]
    return [replace(md, frame_remaining=len(mds) - 1 - i) for i, md in enumerate(mds)]


def test_observations_are_grouped_by_image_and_ambiguous_squares_left_out():
    world = world_from(DOC)
    live = LiveRefinement(world, RefineConfig())
    first, second = _image(world, [0, 1, 2], 1_000), _image(world, [0, 1, 2], 2_000)
    live.add(first[:2], 0)  # the image's last observation not in yet: nothing used
    assert live.refiner.counters["evidence"] == 0
    live.add([second[0], first[2], *second[1:]], 0)  # interleaved images: each used whole
    assert live.refiner.counters["images"] == 2 and live.refiner.counters["evidence"] == 6
    # The image's last observation is of another entity's marker: the image is complete all the same.
    drone_doc = {
        **DOC,
        "entities": {**DOC["entities"], "other": {"markers": [{"id": 9, "size_m": 0.1, "pose": {"pos": [0, 0, 0]}}]}},
    }
    truth = {**TRUTH, "other": pose([0.2, 0.2, 0.0])}
    with_other = world_from(drone_doc)
    live_other = LiveRefinement(with_other, RefineConfig())
    mds = [observe(with_other, truth, 1, m, capture_time_us=5_000) for m in (0, 1, 2, 9)]
    live_other.add([replace(md, frame_remaining=3 - i) for i, md in enumerate(mds)], 0)
    assert live_other.refiner.counters["images"] == 1
    live.add(_image(world, [0, 1, 2], 3_000, ambiguity=0.95), 0)
    assert live.skipped_ambiguous == 3 and live.refiner.counters["images"] == 2
    # An image whose last observation never comes is used once it has waited long enough.
    live.add(_image(world, [0, 1, 2], 4_000)[:2], 0)
    live.step(10**9, Listener(world, make_graph(world)))
    assert live.refiner.counters["rejected_few_markers"] == 1  # two markers: used, but too few


def test_the_refined_world_file_has_the_refined_pose_and_its_sigma(tmp_path):
    import yaml

    truth_world = world_from(DOC)
    moved = {**DOC, "nodes": {"drone": {"system_id": 1}}}
    moved["entities"] = {
        **DOC["entities"],
        "world": {"markers": [dict(m) for m in DOC["entities"]["world"]["markers"]]},
    }
    moved["entities"]["world"]["markers"][2]["pose"] = {"pos": [0.05, 0.6, 0], "rpy_deg": [0, 0, -20]}
    src = tmp_path / "world.yaml"
    src.write_text(yaml.safe_dump(moved, sort_keys=False))
    world, _ = load_node(src, "drone")
    live = LiveRefinement(world, RefineConfig(anchors=(0,)))
    listener = Listener(world, make_graph(world))
    for k in range(30):  # the drone moves: views 0.6 s apart, from several directions
        truth = {"world": pose([0, 0, 0]), "drone": pose([0.3 + 0.02 * k, 0.3 - 0.01 * k, 1.5], [5, 3, 40 + 2 * k])}
        mds = [observe(truth_world, truth, 1, m, capture_time_us=600_000 * k) for m in (0, 1, 2)]
        live.add([replace(md, frame_remaining=2 - i) for i, md in enumerate(mds)], 0)
    for t in range(1, 6):
        live.step(t * 10**9, listener)
    assert live.markers_refined == {2}
    np.testing.assert_allclose(listener.marker_pose(2)[:3, 3], [0, 0.6, 0], atol=1e-4)
    out = tmp_path / "refined.yaml"
    live.write(out)
    written = {m.id: m.T_entity_marker.translation for m in load_world(out).entity("world").markers}
    np.testing.assert_allclose(written[2], [0, 0.6, 0], atol=1e-4)
    np.testing.assert_array_equal(written[1], world.markers[1].T_entity_marker.translation)
    text = out.read_text()
    assert "# anchor: pose as surveyed" in text and "# refined: 1-sigma position" in text
    assert "# kept: pose kept from the input (not refined" in text
    with pytest.raises(AtlasError, match="cannot write the refined map"):
        live.write(tmp_path / "no-such-dir" / "refined.yaml")


def test_refine_settings_are_read_and_checked(tmp_path):
    f = tmp_path / "w.yaml"
    f.write_text(
        NODES.replace("    system_id: 11\n", "    system_id: 11\n    refine: {anchors: [0], write_map: out.yaml}\n")
    )
    _, node = load_node(f, "drone1")
    assert node.refine == RefineConfig(anchors=(0,), write_map=tmp_path / "out.yaml")
    f.write_text(NODES.replace("    system_id: 11\n", "    system_id: 11\n    refine: {anchors: [10]}\n"))
    with pytest.raises(ConfigError, match=r"refine.anchors\[0\].*not a world marker"):
        load_node(f, "drone1")
    f.write_text(NODES)
    assert load_node(f, "drone1")[1].refine is None  # off by default


def test_only_the_given_sensors_observations_are_evidence():
    world = world_from(DOC)
    peers_only = LiveRefinement(world, RefineConfig(), frozenset({7}))  # sensor 1 is a peer's here
    peers_only.add(_image(world, [0, 1, 2], 1_000), 0)
    assert peers_only.refiner.counters["evidence"] == 0
    own = LiveRefinement(world, RefineConfig(), frozenset({1}))
    own.add(_image(world, [0, 1, 2], 1_000), 0)
    assert own.refiner.counters["evidence"] == 3
