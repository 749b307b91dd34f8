"""The world model's lookups and its geometry fingerprint: the same geometry gives the same 32-bit digest
whatever the entities' order, the fusion settings or a quaternion's sign; any change of an id, a size or
a pose by a micrometre changes it."""

from __future__ import annotations

import copy

import pytest

from atlas_onboard.config import parse_world

DOC = {
    "entities": {
        "world": {"markers": [{"id": 1, "size_m": 0.2, "pose": {"pos": [0.0, 0.0, 0.0]}},
                              {"id": 2, "size_m": 0.2, "pose": {"pos": [1.0, 0.0, 0.0]}}]},
        "d1": {"sensors": [{"name": "cam", "id": 10, "pose": {"pos": [0.1, 0.0, 0.0]}}],
               "markers": [{"id": 9, "size_m": 0.1, "pose": {"pos": [0.0, 0.0, 0.1]}}]},
    }
}  # fmt: skip


def test_lookups_by_name_and_id():
    world = parse_world(DOC)
    assert world.entity_names == ("world", "d1")
    assert world.entity("d1").name == "d1"
    with pytest.raises(KeyError):
        world.entity("d2")
    assert set(world.sensors) == {10} and world.sensors[10].entity == "d1"
    assert set(world.markers) == {1, 2, 9} and world.markers[9].entity == "d1"


def _changed(path: list, value) -> dict:
    doc = copy.deepcopy(DOC)
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return doc


def test_the_fingerprint_is_the_geometry_only():
    base = parse_world(DOC).fingerprint()
    assert 0 <= base < 2**32
    reordered = {"entities": dict(reversed(list(copy.deepcopy(DOC)["entities"].items())))}
    assert parse_world(reordered).fingerprint() == base
    assert parse_world({**copy.deepcopy(DOC), "fusion": {"ema_alpha": 0.5}}).fingerprint() == base
    flipped = _changed(
        ["entities", "world", "markers", 1, "pose"],
        {"pos": [1.0, 0.0, 0.0], "rot": {"w": -1.0, "x": 0.0, "y": 0.0, "z": 0.0}},
    )
    assert parse_world(flipped).fingerprint() == base  # q and -q are one rotation


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (["entities", "world", "markers", 1, "id"], 3),
        (["entities", "world", "markers", 1, "size_m"], 0.201),
        (["entities", "world", "markers", 1, "pose"], {"pos": [1.000002, 0.0, 0.0]}),
        (["entities", "d1", "sensors", 0, "id"], 11),
        (["entities", "d1", "sensors", 0, "pose"], {"pos": [0.1, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 1.0]}),
    ],
)
def test_any_change_of_the_geometry_changes_the_fingerprint(path, value):
    assert parse_world(_changed(path, value)).fingerprint() != parse_world(DOC).fingerprint()
