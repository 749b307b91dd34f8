"""The map's marker search: the node's (decimate 2, tracking) finds what the full-resolution search
finds in consecutive frames, as close to the truth, and still counts the ids the world file lacks."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from atlas_onboard.config import load_world
from atlas_onboard.mapping.observations import collect
from tests.mapping.rendered import MAP_WORLD, render_frames, truth_corners, write_folder

LEFT_OUT = 4  # a marker in view that the world file used here does not list
FRAMES = list(range(600, 640))  # 40 consecutive frames of the mapper's flight


@pytest.fixture(scope="module")
def searched(tmp_path_factory: pytest.TempPathFactory):
    tmp = tmp_path_factory.mktemp("search")
    images, intr = render_frames(FRAMES)
    folder, cal = write_folder(tmp, images, intr)
    doc = yaml.safe_load(MAP_WORLD.read_text())
    doc["entities"]["world"]["markers"] = [m for m in doc["entities"]["world"]["markers"] if m["id"] != LEFT_OUT]
    path = tmp / "world.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    world = load_world(path)
    out = {}
    for dec in (1.0, 2.0):
        obs = collect([folder], world, cal, decimate=dec)
        sightings = {
            (obs.frames[f].index, m): c
            for f, m, c in zip(obs.obs_frame, obs.obs_marker_id, obs.corners_px, strict=True)
        }
        out[dec] = (obs, sightings)
    return out


def test_the_node_search_finds_the_full_resolution_sightings_as_exactly(searched) -> None:
    """The node's search (its tracked markers followed without the library, their edges placed on the
    image) finds nearly every sighting of the full-resolution search, and its corners are as close to
    the rendered truth: the same median and 95th percentile of the worst corner's error, within a
    fiftieth of a pixel, and no corner farther than the full-resolution search's farthest."""
    (_, full), (_, node) = searched[1.0], searched[2.0]
    assert set(node) <= set(full)
    assert len(node) >= 0.95 * len(full), (len(node), len(full))
    truth = truth_corners(FRAMES)
    err_full = np.array([np.abs(full[k] - truth[k]).max() for k in node])
    err_node = np.array([np.abs(node[k] - truth[k]).max() for k in node])
    for q in (50, 95):
        assert np.percentile(err_node, q) <= np.percentile(err_full, q) + 0.02, q
    assert err_node.max() <= err_full.max() + 0.02


def test_ids_the_world_file_lacks_are_counted_by_both_searches(searched) -> None:
    (obs_full, _), (obs_node, _) = searched[1.0], searched[2.0]
    assert obs_full.unknown[LEFT_OUT] >= 30  # in view all along
    # Not tracked (the tracker follows listed markers), it is found by the searches of contrast and the
    # periodic whole-image ones: in fewer frames, enough for the report to name it.
    assert obs_node.unknown[LEFT_OUT] >= 0.5 * obs_full.unknown[LEFT_OUT]
    assert LEFT_OUT not in {m for m in obs_node.obs_marker_id}
