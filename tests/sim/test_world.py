"""Which markers the simulated world calls in view: the detector's border rule, with each corner where the
camera images it (a rolling shutter's at its own row's instant), against projections computed here."""

import numpy as np

from atlas_onboard.core.shutter import RowClock
from atlas_onboard.detector.search import BORDER_MARGIN_PX
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.world import SimWorld, marker_corners

TIMES = np.arange(0.0, 20.0, 1 / 30)


def _border_distance(px: np.ndarray, width: int, height: int) -> float:
    """The nearest any of the pixels ``px`` (N, 2) lies to the image's border (negative: outside)."""
    return float(min(px[:, 0].min(), px[:, 1].min(), width - 1 - px[:, 0].max(), height - 1 - px[:, 1].max()))


def test_a_marker_is_in_view_only_with_every_corner_the_detectors_margin_inside():
    """Over a flight whose tags cross the image border, no sighting has a corner nearer the border than the
    detector's margin, and some lie within a pixel of it (the rule, not only the view, decided them)."""
    sim = SimWorld(scenarios.get("rolling-global"))
    nearest = []
    for sid, (_sensor, intr) in sim.cameras.items():
        for t in TIMES[::2]:
            for s in sim.sightings(sid, sim.truth(float(t)), float(t)):
                nearest.append(_border_distance(s.corners_px, intr.width_px, intr.height_px))
    assert len(nearest) > 300
    assert min(nearest) >= BORDER_MARGIN_PX, min(nearest)
    assert sum(d < BORDER_MARGIN_PX + 1 for d in nearest) >= 3


def test_a_rolling_shutter_images_each_corner_at_its_own_rows_instant():
    """Each corner of a rolling-shutter camera's sighting lies where the camera's pose at the instant of the
    row it falls on projects it (25 ms readout, the drone in flight): to a hundredth of a pixel, while the
    stamp's pose alone puts the corners pixels away."""
    sim = SimWorld(scenarios.get("rolling"))
    checked, worst, moved = 0, 0.0, 0.0
    for sid, (sensor, intr) in sim.cameras.items():
        assert sensor.camera is not None and sensor.camera.readout_ms > 0
        clock = RowClock(sensor.camera.readout_ms / 1000.0, intr.height_px)
        M_entity_sensor = sensor.T_entity_sensor.as_matrix()
        for t in TIMES[::3]:
            truth = sim.truth(float(t))
            for s in sim.sightings(sid, truth, float(t)):
                corners = marker_corners(s.marker.size_m)
                for corner, px in zip(corners, s.corners_px, strict=True):
                    t_row = float(t + clock.dt_s(np.array([px[1]]))[0])
                    at_row = sim.truth(t_row)
                    M_world_sensor = at_row[sensor.entity].as_matrix() @ M_entity_sensor
                    M_world_marker = at_row[s.marker.entity].as_matrix() @ s.marker.T_entity_marker.as_matrix()
                    p = np.linalg.inv(M_world_sensor) @ M_world_marker @ np.r_[corner, 1.0]
                    worst = max(worst, float(np.linalg.norm(intr.project(p[None, :3])[0] - px)))
                    checked += 1
                at_stamp = intr.project(corners @ s.M_sensor_marker[:3, :3].T + s.M_sensor_marker[:3, 3])
                moved = max(moved, float(np.abs(at_stamp - s.corners_px).max()))
    assert checked > 400
    assert worst < 0.01, worst
    assert moved > 1.0, moved
