"""The room renderer's rolling shutter: with every row at one pose it draws the global shutter's frame;
the frame's rows are timed as the camera settings say (the stamp is the middle row's mid-exposure)."""

from dataclasses import replace

import numpy as np
import pytest

from atlas_onboard.sim import scenarios
from atlas_onboard.sim.camera import FrameRenderer
from atlas_onboard.sim.room import RowPoses
from atlas_onboard.sim.world import SimWorld


def _renderer(name: str, **camera) -> FrameRenderer:
    sc = scenarios.get(name)
    world = sc.world()
    sid = next(iter(SimWorld(sc, world).cameras))
    sensor = world.sensors[sid]
    if camera:
        sensor = replace(sensor, camera=replace(sensor.camera, **camera))
    return FrameRenderer(sc, world, sensor, seed=7)


def test_rows_at_one_pose_render_the_global_shutter_frame():
    r = _renderer("rolling-global")
    t = 200 / r.fps
    M = r.sensor_poses(np.array([t - 0.004, t, t + 0.004]))
    entities = {name: T.as_matrix() for name, T in r.sim.truth(t).items()}
    still = r.room.render(M[1], M[0], M[2], entities, seed=3)
    h = r.intr.height_px
    rows = RowPoses(np.tile(M[1], (h, 1, 1)), np.tile(M[0], (h, 1, 1)), np.tile(M[2], (h, 1, 1)))
    rolled = r.room.render(M[1], M[0], M[2], entities, seed=3, rows=rows)
    diff = np.abs(still.astype(int) - rolled.astype(int))
    assert diff.mean() < 0.01 and diff.max() <= 3  # float rounding, through the JPEG


@pytest.mark.parametrize("order", ["top_down", "bottom_up"])
def test_row_times_put_the_middle_row_at_the_stamp(order):
    r = _renderer("rolling", readout_order=order)
    times = r.row_times(1.0)
    first, last = (0, -1) if order == "top_down" else (-1, 0)
    assert times[first] == pytest.approx(1.0 - 0.0125) and times[last] == pytest.approx(1.0 + 0.0125)
    assert np.mean(times[[len(times) // 2 - 1, len(times) // 2]]) == pytest.approx(1.0)
    assert np.all(np.diff(times) > 0) == (order == "top_down")


def test_a_rolling_frame_differs_from_its_global_twin_only_by_the_motion():
    rolling, still = _renderer("rolling"), _renderer("rolling-global")
    hover = rolling(0)  # the same scene: the frames differ by the readout's motion only
    assert np.abs(hover.astype(int) - still(0).astype(int)).mean() > 0.5
    assert np.array_equal(_renderer("rolling", readout_ms=0.0)(0), still(0))


def test_cameras_in_one_room_share_its_textures_and_render_what_fresh_ones_do():
    from atlas_onboard.sim import room

    sc = scenarios.get("relay-follow")
    world = sc.world()
    a, b = (FrameRenderer(sc, world, world.sensors[sid], seed=7) for sid in SimWorld(sc, world).cameras)
    assert a.room is not None and b.room is not None and a.room.atlas is b.room.atlas
    shared = a(40)
    room._atlases.clear()  # a camera made with newly made textures draws the same frame, bit for bit
    fresh = FrameRenderer(sc, world, a.sensor, seed=7)
    assert fresh.room is not None and fresh.room.atlas is not a.room.atlas
    assert np.array_equal(fresh(40), shared)
