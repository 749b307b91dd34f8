"""The run's cameras are rendered before it starts: the stored frames are exactly the images the
camera would render live at each frame time, and a node reads them by frame index."""

import numpy as np

from atlas_onboard.sim import scenarios
from atlas_onboard.sim.camera import FrameRenderer, camera_seed, frames_path, prerender


def test_prerendered_frames_are_the_live_renders(tmp_path):
    sc = scenarios.get("gaps")
    world = sc.world()
    n = prerender(sc, sc.world_path(), 3, 2.0, tmp_path)
    sensor = next(s for s in world.sensors.values() if s.camera is not None)
    frames = np.load(frames_path(tmp_path, sensor.id), mmap_mode="r")
    assert n == len(frames) == int(2.0 * sensor.camera.fps) + 2
    assert frames.shape[1:] == (sensor.camera.height_px, sensor.camera.width_px)
    live = FrameRenderer(sc, world, sensor, camera_seed(3, sensor.id))
    for j in (0, 7, len(frames) - 1):  # frames from both workers' halves
        np.testing.assert_array_equal(frames[j], live(j))
    # Not blank: the drone flies over tags, so some frames hold markers (black and white cells).
    assert max(int(frames[j].max()) - int(frames[j].min()) for j in range(len(frames))) > 150
