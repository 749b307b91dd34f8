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


def test_frames_are_reused_by_a_run_no_longer_of_the_same_scenario_and_seed(monkeypatch):
    from atlas_onboard.sim import runner

    monkeypatch.setattr(runner, "_FRAME_CACHE", {})
    sc = scenarios.get("gaps")  # one 640x480 camera
    said = []
    first = runner._rendered_frames(sc, 4, 1.0, said.append)
    kept = {f.name: np.load(f) for f in first.iterdir()}
    assert kept and said == ["rendering the cameras' images"]
    assert runner._rendered_frames(sc, 4, 0.5, said.append) == first  # a prefix of what is there
    assert said[-1].startswith("reusing")
    other_seed = runner._rendered_frames(sc, 5, 0.5, said.append)
    assert other_seed != first and first.exists()
    longer = runner._rendered_frames(sc, 4, 1.5, said.append)
    assert longer != first and not first.exists()  # replaced, not kept twice
    for name, frames in kept.items():  # frame j is the same image in the longer run
        np.testing.assert_array_equal(np.load(longer / name, mmap_mode="r")[: len(frames)], frames)
    runner._drop_frame_cache()
    assert not longer.exists() and not other_seed.exists() and runner._FRAME_CACHE == {}
