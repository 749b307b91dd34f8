"""``atlas-onboard run``'s start-up: camera sources that are not devices or files are plug-ins registered
by kind (the simulator's ``sim``); start-up itself knows none of them."""

import pytest

from atlas_onboard.config import NodeConfig, parse_world
from atlas_onboard.errors import AtlasError
from atlas_onboard.service import run as service_run

WORLD = {
    "entities": {
        "d1": {
            "sensors": [
                {"name": "a", "id": 1, "pose": {}, "camera": {"source": "fake"}},
                {"name": "b", "id": 2, "pose": {}},  # fed by peers: no camera
                {"name": "c", "id": 3, "pose": {}, "camera": {"source": "fake", "fps": 7}},
            ]
        }
    }
}


def test_a_registered_kind_makes_the_cameras_of_its_sensors(monkeypatch):
    monkeypatch.setattr(service_run, "CAMERA_KINDS", {})
    world, config = parse_world(WORLD), NodeConfig(entity="d1", system_id=1)
    made = []
    service_run.register_camera_kind("fake", lambda w, c, s: made.append((w, c, s.id, s.camera.fps)) or s.name)
    assert service_run.build_cameras(world, config) == ["a", "c"]
    assert made == [(world, config, 1, 0.0), (world, config, 3, 7.0)]


def test_an_unregistered_kind_is_a_device_or_file_that_needs_its_calibration(monkeypatch):
    monkeypatch.setattr(service_run, "CAMERA_KINDS", {})
    with pytest.raises(AtlasError, match=r"sensor d1\.a: camera\.calibration is required for 'fake'"):
        service_run.build_cameras(parse_world(WORLD), NodeConfig(entity="d1", system_id=1))
