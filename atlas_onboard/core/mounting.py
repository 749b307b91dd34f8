"""Which frame mistake makes the vision attitude disagree with the autopilot's (bench check).

Both attitudes are NED/FRD, the autopilot's from its own sensors, the vision one as the node sends it.
Gravity is the one direction both know: the up vector in the body frame, ``u = R_ned_frd^T (0, 0, -1)``.
A mistake in the world file changes the vision attitude in one of two ways:

- in the body (a camera's mounting in the file turned about its optical axis from the real one, body
  axes written FLU but declared FRD or the reverse): ``R_vis = R_true D``, so ``u_vis = D^T u_true``;
- in the world (a world file written in NED but declared ENU, or the reverse): ``R_vis = W R_true``
  with ``W`` turning up into down, so ``u_vis = -u_true``.

Each candidate predicts ``u_vis`` from ``u_ap``; the one whose prediction is nearest (mean angle over
the samples) names the likely cause. Rotations about the vertical leave gravity where it is: on a level
bench a camera looking down turned about its optical axis looks like a correct one (reported as not
seen, with the way to see it: tilt the drone).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

UP_NED = np.array([0.0, 0.0, -1.0])
AGREE_DEG = 3.0  # two attitudes within this of each other agree (the autopilot's own error is ~1 deg)
DISTINCT_DEG = 2.0 * AGREE_DEG  # a candidate predicting gravity this far from the correct setup's can be told apart


@dataclass(frozen=True, slots=True)
class Candidate:
    """One possible frame mistake: its name, how to fix it, and what it does to the attitude."""

    name: str
    fix: str
    D_body: Rotation  # R_vis = R_true D (FRD body)
    world_flip: bool  # R_vis = W R_true with W turning up into down
    short: str = ""  # the name in a few words (a STATUSTEXT carries 50 characters)


@dataclass(frozen=True, slots=True)
class Diagnosis:
    """The candidates ranked by how well they explain the samples."""

    ranked: tuple[tuple[Candidate, float], ...]  # (candidate, mean angle in deg), best first
    roll_diff_deg: float  # vision minus autopilot, median over the samples
    pitch_diff_deg: float
    tilt_deg: float  # the autopilot's median tilt from level
    hidden: tuple[Candidate, ...]  # mistakes this data cannot tell from a correct setup

    @property
    def best(self) -> Candidate:
        return self.ranked[0][0]


def candidates(optical_axes_frd: dict[str, NDArray[np.float64]]) -> list[Candidate]:
    """The correct setup first, then the mistakes: each camera turned by 90, -90 or 180 deg about its
    optical axis (``optical_axes_frd``: camera name -> unit optical axis in the body, FRD), the body
    axes' convention swapped, the world's convention swapped."""
    out = [Candidate("correct", "", Rotation.identity(), False)]
    for name, axis in optical_axes_frd.items():
        a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
        for deg in (90.0, -90.0, 180.0):
            # The file's mounting turned by deg about the optical axis from the real one: vision's body
            # is the real body turned by -deg about that axis.
            out.append(
                Candidate(
                    f"the world file turns camera {name} {deg:+.0f} deg about its optical axis from where it is",
                    f"turn sensor {name}'s pose in the world file by {-deg:+.0f} deg about the optical axis (its"
                    " mount frame's x axis), or turn the camera on the drone to match the file",
                    Rotation.from_rotvec(math.radians(-deg) * a),
                    False,
                    f"{name} mount {deg:+.0f}deg about axis",
                )
            )
    for name, axis in optical_axes_frd.items():
        # Declared FRD, the numbers FLU (or the reverse): the body and the camera's mount frame (both in
        # the file's body convention) are each turned 180 deg about their x axis, the mount's being the
        # optical axis: D = R_a(180) R_x(180). A camera looking along x is unaffected.
        a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
        D = Rotation.from_rotvec(math.pi * a) * Rotation.from_euler("x", 180.0, degrees=True)
        if D.magnitude() > 1e-6:
            out.append(
                Candidate(
                    f"body axes written in FLU but declared FRD (or the reverse; seen through camera {name})",
                    "set conventions.body to the convention the sensor poses are written in (FLU: x forward,"
                    " y left, z up; FRD: x forward, y right, z down)",
                    D,
                    False,
                    "body FLU/FRD swapped",
                )
            )
    out.append(
        Candidate(
            "world file written in NED but declared ENU (or the reverse): up and down swapped",
            "set conventions.world to the convention the marker poses are written in (ENU: z up; NED: z down)",
            Rotation.identity(),
            True,
            "world NED/ENU swapped",
        )
    )
    return out


def up_vectors(R_ned_frd: Rotation) -> NDArray[np.float64]:
    """The up direction in the body (FRD), shape (N, 3), of a stack of NED/FRD attitudes."""
    return np.atleast_2d(R_ned_frd.inv().apply(UP_NED))


def _predict(c: Candidate, u_ap: NDArray[np.float64]) -> NDArray[np.float64]:
    u = c.D_body.inv().apply(u_ap)
    return -u if c.world_flip else u


def _angles_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _roll_pitch_deg(R: Rotation) -> NDArray[np.float64]:
    ypr = np.atleast_2d(R.as_euler("ZYX", degrees=True))
    return ypr[:, [2, 1]]


def diagnose(R_autopilot: Rotation, R_vision: Rotation, cands: list[Candidate]) -> Diagnosis:
    """Rank ``cands`` by the mean angle between the gravity each predicts for vision and the one vision
    shows, over paired samples (``R_autopilot[k]`` and ``R_vision[k]``: NED/FRD at the same time)."""
    u_ap, u_vis = up_vectors(R_autopilot), up_vectors(R_vision)
    scored = sorted(((c, float(np.mean(_angles_deg(_predict(c, u_ap), u_vis)))) for c in cands), key=lambda x: x[1])
    correct = next(c for c in cands if c.name == "correct")
    hidden = tuple(
        c for c in cands
        if c is not correct and float(np.mean(_angles_deg(_predict(c, u_ap), _predict(correct, u_ap)))) < DISTINCT_DEG
    )  # fmt: skip
    diff = _roll_pitch_deg(R_vision) - _roll_pitch_deg(R_autopilot)
    diff = (diff + 180.0) % 360.0 - 180.0
    tilt = _angles_deg(u_ap, np.tile(UP_NED, (len(u_ap), 1)))  # level: up is body -z (FRD)
    return Diagnosis(
        tuple(scored), float(np.median(diff[:, 0])), float(np.median(diff[:, 1])), float(np.median(tilt)), hidden
    )


def yaw_difference_deg(R_autopilot: Rotation, R_vision: Rotation) -> float:
    """Vision's heading minus the autopilot's, deg in (-180, 180], the circular mean over the samples."""
    d = R_vision.as_euler("ZYX")[..., 0] - R_autopilot.as_euler("ZYX")[..., 0]
    return float(np.degrees(math.atan2(float(np.mean(np.sin(d))), float(np.mean(np.cos(d))))))
