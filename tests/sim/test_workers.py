"""The simulator's geometric detector (:func:`atlas_onboard.sim.workers.geometric_detector`): true corners
plus pixel noise, posed as the real detector's pose stage poses them. Its 6x6 covariance is checked
against the truth over many noise draws of one known view, with the chi-square's figures."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import exp1
from scipy.stats import chi2

from atlas_onboard.core.markerdata import upper_to_matrix
from atlas_onboard.detector.rotations import matrix_from_quat, rotvec_from_matrix
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.workers import NOISE_PX, geometric_detector
from atlas_onboard.sim.world import Sighting, SimWorld

DRAWS = 2000
SIGMAS = 4.0  # the band's half-width in standard errors of the mean of DRAWS

# The NEES of an honest first-order covariance is chi2(6). The pose stage scales a covariance by the fit's
# own chi-square over the 2 degrees of freedom a pose leaves of 8 residuals, when it is larger than 1
# (pose.fitted_covariance); that chi2(2) / 2 is independent of the pose's error, so each NEES is divided
# by max(1, Y), Y ~ Exp(1), whose inverse has mean 1 - 1/e + E1(1). An honest covariance has its mean
# NEES between the two.
NEES_SCALED = 6.0 * (1.0 - math.exp(-1.0) + float(exp1(1.0)))
NEES_BAND = SIGMAS * math.sqrt(2.0 * 6.0 / DRAWS)  # chi2(6)'s variance is 12
WITHIN = 0.99  # the chi2(6) quantile whose share of the draws is checked
WITHIN_BAND = SIGMAS * math.sqrt(WITHIN * (1.0 - WITHIN) / DRAWS)

# (scenario, camera as entity.sensor, time s, marker id): known views of the scenarios' geometry
VIEWS = {
    "face-on follower": ("relay", "drone_b.front", 2.0, 50),  # 1 m, 1 degree off its axis: the ambiguous case
    "tilted floor tag": ("relay", "drone_a.down", 2.0, 1),  # 1.3 m, 31 degrees
    "image corner, k1 -0.12": ("map", "mapper2.cam", 12.75, 0),  # a corner at 1.16 cx from the centre
}


def _view(scenario: str, camera: str, t: float, marker_id: int) -> tuple[SimWorld, int, Sighting]:
    world = SimWorld(scenarios.get(scenario))
    sid = next(i for i, (s, _) in world.cameras.items() if f"{s.entity}.{s.name}" == camera)
    sighting = next(s for s in world.sightings(sid, world.truth(t), t) if s.marker.id == marker_id)
    return world, sid, sighting


def _nees(world: SimWorld, sid: int, sighting: Sighting, t: float) -> np.ndarray:
    """Pose NEES ([dp, dtheta], dtheta about the marker's axes) of each draw's detection against the truth."""
    sensor, intr = world.cameras[sid]
    M = sighting.M_sensor_marker
    out = []
    for seed in range(DRAWS):
        found = geometric_detector(None, sensor, intr, seed).detect(t, [sighting], {"epoch": 0.0})  # type: ignore[arg-type]
        assert len(found) == 1
        md = found[0]
        w, x, y, z = md.q_sensor_marker_wxyz
        R = matrix_from_quat(np.array([x, y, z, w]))
        d = np.concatenate([M[:3, 3] - np.array(md.p_sensor_marker_m), rotvec_from_matrix(R.T @ M[:3, :3])])
        out.append(float(d @ np.linalg.solve(upper_to_matrix(np.array(md.covariance)), d)))
    return np.array(out)


@pytest.mark.parametrize("name", list(VIEWS))
def test_single_marker_covariance_is_honest(name: str) -> None:
    scenario, camera, t, marker_id = VIEWS[name]
    world, sid, sighting = _view(scenario, camera, t, marker_id)
    nees = _nees(world, sid, sighting, t)
    assert NEES_SCALED - NEES_BAND <= nees.mean() <= 6.0 + NEES_BAND, f"{name}: mean NEES6 {nees.mean():.2f}"
    share = float(np.mean(nees <= chi2.ppf(WITHIN, 6)))
    assert share >= WITHIN - WITHIN_BAND, f"{name}: {share:.4f} within chi2(6)'s {WITHIN} quantile"


def test_noise_is_the_corner_model() -> None:
    """The corners the pose is solved from are the truth plus NOISE_PX per axis: the reprojection error the
    detection reports is the fit's RMS residual, whose square has mean NOISE_PX^2 (8 - 6) / 4 undistorted."""
    world, sid, sighting = _view(*VIEWS["tilted floor tag"])
    sensor, intr = world.cameras[sid]
    errs = [
        geometric_detector(None, sensor, intr, seed).detect(2.0, [sighting], {"epoch": 0.0})[0].reprojection_error_px  # type: ignore[arg-type]
        for seed in range(DRAWS)
    ]
    mean_sq = float(np.mean(np.square(errs)))
    expected = NOISE_PX**2 * 2.0 / 4.0
    # chi2(2) / 4 NOISE_PX^2 per draw: its mean's standard error is sqrt(4 / DRAWS) / 4 NOISE_PX^2
    assert abs(mean_sq - expected) <= SIGMAS * math.sqrt(4.0 / DRAWS) / 4.0 * NOISE_PX**2
