"""Building a map from synthetic observations: markers that do not fit (moved, wrong size) are named,
the gravity anchor sets the origin and the vertical, no anchor seen is refused, and a group never seen
with an anchor is reported while the rest is mapped."""

from __future__ import annotations

import numpy as np
import pytest

from atlas_onboard.mapping.build import MapError, MapOptions, build_map
from tests.mapping.synthetic import make_observations


def test_a_marker_moved_during_the_recording_is_named_and_left_out() -> None:
    obs, world, M_true = make_observations(1, n_frames=80, moved=(5, 0.10))
    res = build_map(obs, world, MapOptions(anchors=(0,)))
    assert res.markers[5].status == "moved"
    assert "moved by" in res.markers[5].detail
    assert 5 not in res.mapped()
    bad = [m for m, r in res.markers.items() if r.status in ("moved", "wrong_size", "duplicated")]
    assert bad == [5]
    # The others are mapped as if it had not been there: each within what its sigma says.
    for m, M in res.mapped().items():
        sigma = np.linalg.norm(res.markers[m].sigma_m)
        assert np.linalg.norm(M[:3, 3] - M_true[m][:3, 3]) < 4 * sigma + 0.001, m


def test_a_marker_printed_at_the_wrong_size_is_named_with_its_size() -> None:
    obs, world, _ = make_observations(1, n_frames=80, true_size=(7, 0.19))  # the world file says 160 mm
    res = build_map(obs, world, MapOptions(anchors=(0,)))
    assert res.markers[7].status == "wrong_size"
    fitted_mm = float(res.markers[7].detail.split("fit a marker of ")[1].split(" mm")[0])
    assert abs(fitted_mm - 190.0) < 3.0
    assert [m for m, r in res.markers.items() if r.status in ("moved", "wrong_size", "duplicated")] == [7]


def test_gravity_anchor_makes_its_marker_the_origin_and_up_the_vertical() -> None:
    """Marker 2 lies on the floor, turned about the vertical: the map's world has its origin and
    heading, and is level by the attitudes (not by the anchor's own tilt, which its few corners give
    to a fraction of a degree only)."""
    obs, world, M_true = make_observations(4, n_frames=60, attitude=True)
    res = build_map(obs, world, MapOptions(gravity_anchor=2))
    M_anchor_world = np.linalg.inv(M_true[2])
    assert np.allclose(res.markers[2].M_world_marker[:3, 3], 0.0, atol=1e-12)
    tilts = []
    for m, M in res.mapped().items():
        expected = M_anchor_world @ M_true[m]
        sigma = np.linalg.norm(res.markers[m].sigma_m)
        assert np.linalg.norm(M[:3, 3] - expected[:3, 3]) < 4 * sigma + 0.002, m
        if m < 9:  # the floor markers: their faces look straight up
            tilts.append(np.degrees(np.arccos(np.clip(M[2, 2], -1, 1))))
    assert np.median(tilts) < 0.4, tilts
    # The same data anchored on marker 2 alone (its own tilt taken as level) tilts the whole floor.
    fixed = build_map(obs, world, MapOptions(anchors=(2,)))
    tilts_fixed = [np.degrees(np.arccos(np.clip((M_anchor_world @ M)[2, 2], -1, 1)))
                   for m, M in fixed.mapped().items() if m < 9 and m != 2]  # fmt: skip
    assert np.median(tilts_fixed) > np.median(tilts), (tilts_fixed, tilts)


def test_no_anchor_seen_is_refused() -> None:
    obs, world, _ = make_observations(2, n_frames=40, hidden={0})
    with pytest.raises(MapError, match="no anchor seen"):
        build_map(obs, world, MapOptions(anchors=(0,)))


def test_a_group_without_an_anchor_is_reported_and_the_rest_mapped() -> None:
    """The synthetic room with its wall never seen with the floor: anchored on the floor only, the
    wall's markers are reported unanchored; anchored on both, each is within its sigma of the truth."""
    obs, world, M_true = make_observations(3, n_frames=120)
    wall = {9, 10, 11}
    keep = [not (obs.obs_marker_id[i] in wall and any(
        obs.obs_frame[j] == obs.obs_frame[i] and obs.obs_marker_id[j] not in wall for j in range(len(obs.obs_frame))))
        for i in range(len(obs.obs_frame))]  # fmt: skip
    for name in ("obs_frame", "obs_marker_id", "corners_px"):
        setattr(obs, name, [v for v, k in zip(getattr(obs, name), keep, strict=True) if k])
    floor_only = build_map(obs, world, MapOptions(anchors=(0,)))
    assert {floor_only.markers[m].status for m in wall} == {"unanchored"}
    assert not wall & set(floor_only.mapped()) and set(range(9)) <= set(floor_only.mapped())
    both = build_map(obs, world, MapOptions(anchors=(0, 10)))
    assert set(range(12)) <= set(both.mapped())
    for m in (9, 11):
        sigma = np.linalg.norm(both.markers[m].sigma_m)
        assert np.linalg.norm(both.mapped()[m][:3, 3] - M_true[m][:3, 3]) < 4 * sigma + 0.002, m
