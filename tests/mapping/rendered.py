"""Rendered frames of the simulator's map scenario, as an image folder with its calibration: shared by
the map command's tests and the map's marker search tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

MAP_WORLD = Path(__file__).resolve().parents[2] / "atlas_onboard" / "sim" / "scenarios" / "map.yaml"


def render_frames(frames: list[int], sensor_id: int = 1) -> tuple[list[np.ndarray], object]:
    from atlas_onboard.sim import scenarios
    from atlas_onboard.sim.camera import FrameRenderer

    scenario = scenarios.get("map")
    world = scenario.world()
    renderer = FrameRenderer(scenario, world, world.sensors[sensor_id], seed=7)
    return [renderer(j) for j in frames], renderer.intr


def truth_corners(frames: list[int], sensor_id: int = 1) -> dict[tuple[int, int], np.ndarray]:
    """The true corners (4, 2) (distorted pixels, OpenCV order) of every marker in view in the frames of
    :func:`render_frames`, by (the frame's place in ``frames``, marker id)."""
    from atlas_onboard.detector.pose import object_corners
    from atlas_onboard.sim import scenarios
    from atlas_onboard.sim.camera import FrameRenderer

    scenario = scenarios.get("map")
    world = scenario.world()
    renderer = FrameRenderer(scenario, world, world.sensors[sensor_id], seed=7)
    out = {}
    for k, j in enumerate(frames):
        t = j / renderer.fps
        for s in renderer.sim.sightings(sensor_id, renderer.sim.truth(t), t):
            M = s.T_sensor_marker.as_matrix()
            out[(k, s.marker.id)] = renderer.intr.project(object_corners(s.marker.size_m) @ M[:3, :3].T + M[:3, 3])
    return out


def write_folder(tmp: Path, images: list[np.ndarray], intr: object) -> tuple[Path, Path]:
    from atlas_onboard.sim.runner import write_calibration

    folder = tmp / "frames"
    folder.mkdir()
    for k, img in enumerate(images):
        cv2.imwrite(str(folder / f"frame{k:04d}.png"), img)
    cal = tmp / "calibration.yaml"
    write_calibration(cal, intr)  # type: ignore[arg-type]
    return folder, cal
