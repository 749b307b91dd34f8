"""The 6x6 covariance a relay's drones publish is honest as a whole (rendered frames, the real
detector, listener and graph of each drone's node, the 21 floats of the message as float32)."""

import numpy as np

from atlas_onboard.sim import offline


def test_relay_publishes_positive_definite_6x6_whose_pose_nees_is_about_6():
    """drone_a over the floor tags, drone_b seeing only drone_a's tag, drone_c only drone_b's: each
    drone's published 6x6 (NED/FRD, float32 on the wire) is positive definite, and the pose NEES of
    what all three publish averages about its dimension 6 (cross terms included: a 6x6 whose cross
    terms are wrong gives a NEES far from 6 even when its diagonal is right)."""
    _, outputs = offline.run("relay", frames=24)
    assert all(s.not_positive_definite == 0 for s in outputs.values())
    assert all(len(s.errors) >= 15 for s in outputs.values()), {d: len(s.errors) for d, s in outputs.items()}
    nees6 = np.concatenate([s.nees() for s in outputs.values()])
    within = np.mean([np.abs(e) <= 3 * np.sqrt(np.diag(C)) for s in outputs.values() for e, C in s._pairs()], axis=0)
    per_drone = {d: round(float(s.nees().mean()), 2) for d, s in outputs.items()}
    assert 3.0 <= nees6.mean() <= 9.0, (nees6.mean(), per_drone)
    assert np.all(within >= 0.95), within
