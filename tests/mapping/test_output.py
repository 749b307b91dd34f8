"""The written world file: the map's poses in the file's own convention, read back equal."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from atlas_onboard.config import load_world


@pytest.mark.parametrize("convention", ["ENU", "NED"])
def test_the_written_world_file_loads_back_to_the_mapped_poses(tmp_path: Path, convention: str) -> None:
    """The map's poses (internal ENU) are written in the file's own convention, and read back equal."""
    from scipy.spatial.transform import Rotation

    from atlas_onboard.mapping.build import MapResult, MarkerReport
    from atlas_onboard.mapping.output import world_text

    src = tmp_path / "world.yaml"
    src.write_text(
        f"conventions: {{world: {convention}, body: FLU}}\n"
        "entities:\n  world:\n    markers:\n"
        "      - {id: 1, size_m: 0.2, pose: {pos: [0, 0, 0]}}\n"
        "      - {id: 2, size_m: 0.2, family: DICT_4X4_50, pose: {pos: [1, 2, 3]}}\n"
        "  drone:\n    markers:\n      - {id: 9, size_m: 0.1, pose: {pos: [0, 0, 0.1]}}\n"
    )
    world = load_world(src)
    M = np.eye(4)
    M[:3, :3] = Rotation.from_euler("xyz", [10, -20, 75], degrees=True).as_matrix()
    M[:3, 3] = [1.2345, -0.5, 2.0]
    markers = {
        1: MarkerReport(1, 0.2, 50, "mapped", M, (0.001, 0.001, 0.002), (0.1, 0.1, 0.1), 0.2, 30.0),
        2: MarkerReport(2, 0.2, 0, "not_seen"),
    }
    result = MapResult(markers, np.zeros(0), [], None, 0.1, {}, {}, 10, 0, 0)
    out = tmp_path / "out.yaml"
    out.write_text(world_text(world, result, "test"))
    back = load_world(out)
    assert np.allclose(back.markers[1].T_entity_marker.as_matrix(), M, atol=1e-6)
    assert np.allclose(back.markers[2].T_entity_marker.as_matrix(), world.markers[2].T_entity_marker.as_matrix())
    assert back.markers[2].family == "DICT_4X4_50" and back.markers[9].entity == "drone"
    assert "1-sigma position [1.00, 1.00, 2.00] mm" in out.read_text()
