"""A parent's pose at its child's capture time: every edge at the right time.

A candidate through another entity (a drone seen by a drone) composes that parent's fused pose, taken
at the instants of the parent's own observations, with an edge taken at the child's camera's instant,
tens of milliseconds apart. :class:`MotionHistory` keeps each vertex's last fused poses (one per
capture time) and gives the parent's pose at any instant by a least-squares line through the newest
ones (position, and rotation vectors about the newest attitude), each weighed by the inverse of the
variance it would give the child: between two of them an interpolation,
past the newest an extrapolation with the velocity and turn rate they show. The result is a linear
combination of the samples, ``x(t) = sum_i w_i x_i`` with ``sum_i w_i = 1`` and ``sum_i w_i t_i = t``,
so its covariance is exact for independent samples, ``sum_i w_i^2 C_i``, and a line misses a path
that accelerates by ``a`` by exactly ``a / 2 sum_i w_i (t_i - t)^2``: that is the model's term, with
the manoeuvre acceleration's spread (:data:`ACCEL_SIGMA_M_S2`, :data:`ANGULAR_ACCEL_SIGMA_RAD_S2`).
The number of samples is chosen from these variances alone (never from the values), the one that
leaves the child the least position variance. docs/covariance.md has the design.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

ACCEL_SIGMA_M_S2 = 1.5
"""Spread of a quadrotor's manoeuvre acceleration per axis (the EKF's Singer process: 1.5 m/s^2)."""

ANGULAR_ACCEL_SIGMA_RAD_S2 = 5.0
"""Spread of a quadrotor's angular acceleration per axis: an airframe's vibration of 0.3 deg at
3-8 Hz alone is 2-13 rad/s^2 (amplitude times the angular frequency squared)."""

MAX_SAMPLES = 6  # a line through at most this many poses (a fifth of a second at 30 Hz)
WINDOW_US = 300_000  # and none older than this before the newest: beyond, a line says nothing
WAIT_US = 100_000
"""How far past its parent's newest pose a child's view that cannot be placed yet (the parent's next pose
is due, or the extrapolation passes the relayed limit) waits for the parent's next one, at least: a
network's 10-50 ms and a frame at 15 Hz. A parent whose poses come late (its node or its link slower
than the child's camera path) is waited for by its measured lateness more, up to ``MAX_WAIT_US``."""
MAX_WAIT_US = 250_000
"""The longest a view waits for a late parent (the autopilots take vision up to 250-300 ms old)."""
LAG_WINDOW_US = 1_000_000
"""A parent's lateness is the least of its children's views' leads over its newest pose in this long
(a second: a gap in the parent's own views makes them lead by more, not less)."""
MAX_WAITING = 4  # views of a child kept waiting at once (the oldest goes first)


@dataclass(frozen=True, slots=True)
class Sample:
    """One fused pose of a vertex: capture time (us), position, orientation xyzw, 6x6 covariance."""

    t_us: int
    p: NDArray[np.float64]
    q: NDArray[np.float64]
    cov: NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Aligned:
    """A vertex's pose moved to another instant: position, orientation xyzw, 6x6 covariance."""

    p: NDArray[np.float64]
    q: NDArray[np.float64]
    cov: NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Parents:
    """Each candidate's parent at the candidate's capture time, shapes (N, ...): position ``p``,
    orientation ``q`` xyzw, 6x6 ``cov``; ``moved``: taken at that time (False: the parent's pose is
    at that time already)."""

    p: NDArray[np.float64]
    q: NDArray[np.float64]
    cov: NDArray[np.float64]
    moved: NDArray[np.bool_]
    wait: NDArray[np.bool_]  # past the parent's newest pose, and its next one is due before: wait for it


@dataclass(frozen=True, slots=True)
class Waiting:
    """A child's view that waits for its parent's next pose: the edge parent -> child as walked (its
    row, the key that held it, ``p``, ``q`` xyzw, aged ``sigma`` and 6x6 ``cov``) and its image's
    ``capture_us``."""

    row: int
    key: tuple[int, int]
    parent: int
    child: int
    p: NDArray[np.float64]
    q: NDArray[np.float64]
    sigma: float
    cov: NDArray[np.float64]
    capture_us: int


class WaitingViews:
    """Each child's views taken just past its parent's newest pose, kept (at most ``max_views`` per
    child, none older than ``window_us`` before the child's newest) until a parent pose after them
    brackets them: they are then placed by interpolation one per evaluation, oldest first, even when
    the child's next image has replaced its edge meanwhile."""

    def __init__(self, max_views: int = MAX_WAITING, window_us: int = MAX_WAIT_US) -> None:
        self.max_views = max_views
        self.window_us = window_us
        self._views: dict[tuple[int, int], deque[Waiting]] = {}

    def clear(self) -> None:
        self._views.clear()

    def add(self, root: int, view: Waiting) -> None:
        """Keep ``view`` (one already held for the same row and image changes nothing)."""
        queue = self._views.setdefault((root, view.child), deque(maxlen=self.max_views))
        if any(w.row == view.row and w.capture_us == view.capture_us for w in queue):
            return
        queue.append(view)

    def pending(self, root: int, child: int, after_us: int, now_us: int) -> bool:
        """Whether ``child`` has a view waiting taken after ``after_us`` (its last pose), before ``now_us``
        (its current image) and no more than the window before it."""
        queue = self._views.get((root, child))
        return bool(queue) and any(after_us < w.capture_us < now_us <= w.capture_us + self.window_us for w in queue)

    def ready(self, root: int, child: int, after_us: int, bracketed: dict[int, int]) -> list[Waiting]:
        """``child``'s views of its oldest image taken after ``after_us`` (its last pose) whose parent's
        newest pose (``bracketed``: capture time per parent) is at or after them: the next to place in
        capture order. These and every older view are forgotten, the newer ones wait for the next call.
        Views older than the window before the newest held are dropped first."""
        queue = self._views.get((root, child))
        if not queue:
            return []
        newest = max(w.capture_us for w in queue)
        kept = [w for w in queue if after_us < w.capture_us and newest - w.capture_us <= self.window_us]
        ok = [w for w in kept if w.parent in bracketed and bracketed[w.parent] >= w.capture_us]
        t = min((w.capture_us for w in ok), default=None)
        queue.clear()
        queue.extend(w for w in kept if t is None or w.capture_us > t)
        return [w for w in ok if w.capture_us == t]


class MotionHistory:
    """The newest fused poses of each vertex, per root of evaluation (see the module)."""

    def __init__(self, max_samples: int = MAX_SAMPLES, window_us: int = WINDOW_US) -> None:
        self.max_samples = max_samples
        self.window_us = window_us
        self._tracks: dict[tuple[int, int], deque[Sample]] = {}
        # Per parent: (capture time, lead over the parent's newest pose) of each new child view, as first seen.
        self._leads: dict[tuple[int, int], deque[tuple[int, int]]] = {}
        self._seen: dict[tuple[int, int], int] = {}  # the newest child view's capture time, per parent

    def clear(self) -> None:
        self._tracks.clear()
        self._leads.clear()
        self._seen.clear()

    def lag_us(self, root: int, v: int, t_us: int) -> int:
        """How late ``v``'s poses come against its children's views: the least lead of a view taken before
        ``t_us`` over ``v``'s newest pose, as each view was first composed, in the ``LAG_WINDOW_US``
        before (0 when a view found its parent's pose already there, or none was seen)."""
        leads = self._leads.get((root, v))
        if not leads:
            return 0
        return max(min((d for t, d in leads if 0 < t_us - t <= LAG_WINDOW_US), default=0), 0)

    def _lead(self, root: int, v: int, t_us: int, track: list[Sample]) -> None:
        """A child view's lead over ``v``'s newest pose, when first seen (composed again after ``v``'s
        next poses came, it leads by less: not the lateness); none while ``v``'s track is starting."""
        key = (root, v)
        if t_us <= self._seen.get(key, -1):
            return
        self._seen[key] = t_us
        if len(track) >= 2:
            self._leads.setdefault(key, deque(maxlen=64)).append((t_us, t_us - track[-1].t_us))

    def add(self, root: int, v: int, sample: Sample) -> None:
        """Remember ``v``'s fused pose (in ``root``'s frame); a capture time already held, or older
        than the newest held, changes nothing."""
        track = self._tracks.setdefault((root, v), deque(maxlen=self.max_samples))
        if track and sample.t_us <= track[-1].t_us:
            return
        track.append(sample)

    def samples(self, root: int, v: int) -> list[Sample]:
        """``v``'s samples no older than the window before its newest, oldest first."""
        track = self._tracks.get((root, v))
        if not track:
            return []
        newest = track[-1].t_us
        return [s for s in track if newest - s.t_us <= self.window_us]

    def at(self, root: int, v: int, t_us: int, lever_m: float) -> Aligned | None:
        """``v``'s pose at ``t_us``, or None when fewer than two samples show its motion. ``lever_m``:
        how far the child is from ``v`` (its attitude variance counts times its square)."""
        track = self.samples(root, v)
        if len(track) < 2:
            return None
        best: tuple[float, Aligned] | None = None
        for n in range(2, len(track) + 1):
            out = _line(track[-n:], t_us, lever_m)
            if out is None:
                continue
            cost = float(np.trace(out.cov[:3, :3]) + lever_m**2 * np.trace(out.cov[3:, 3:]))
            if best is None or cost < best[0]:
                best = (cost, out)
        return None if best is None else best[1]

    def parents(
        self,
        root: int,
        parent: NDArray[np.intp],
        capture_us: NDArray[np.int64],
        p_pc: NDArray[np.float64],
        p: NDArray[np.float64],
        q: NDArray[np.float64],
        cov: NDArray[np.float64],
        stamp_us: NDArray[np.int64],
        age_sigma: tuple[float, float] = (0.0, 0.0),
    ) -> Parents:
        """Each candidate's ``parent`` at its ``capture_us``: along the line of the parent's recent poses
        where they show its motion; elsewhere its newest pose (``p``, ``q``, ``cov``, ``stamp_us``: per
        vertex), aged by the time between (``age_sigma``: m/s and rad/s, each 1-sigma of an unknown
        motion, as an edge is aged). ``p_pc``: the child in the parent's frame (the lever arm of the
        parent's attitude)."""
        out_p, out_q, out_cov = p[parent].copy(), q[parent].copy(), cov[parent].copy()
        moved = np.zeros(len(parent), dtype=bool)
        wait = np.zeros(len(parent), dtype=bool)
        lever = np.linalg.norm(p_pc, axis=1)
        idx = np.arange(3)
        for i, (v, t) in enumerate(zip(parent.tolist(), capture_us.tolist(), strict=True)):
            track = self.samples(root, v)
            lag = self.lag_us(root, v, t)  # from the views before this one
            self._lead(root, v, t, track)
            if t == stamp_us[v]:
                continue
            moved[i] = True
            if len(track) >= 2 and t > track[-1].t_us:
                # The parent's next pose is due before this view's time: its spacing, and its lateness.
                spacing = float(np.median(np.diff([s.t_us for s in track])))
                ahead = t - track[-1].t_us
                wait[i] = ahead < spacing + lag and ahead <= MAX_WAIT_US
            at = self.at(root, v, t, float(lever[i]))
            if at is not None:
                out_p[i], out_q[i], out_cov[i] = at.p, at.q, at.cov
            else:  # its motion unknown: where it was, with what it may have moved since
                dt_s = abs(t - int(stamp_us[v])) / 1e6
                out_cov[i, idx, idx] += (age_sigma[0] * dt_s) ** 2
                out_cov[i, idx + 3, idx + 3] += (age_sigma[1] * dt_s) ** 2
        return Parents(out_p, out_q, out_cov, moved, wait)

    def newest(self, root: int, v: int) -> Sample | None:
        """``v``'s newest fused pose, if any."""
        track = self._tracks.get((root, v))
        return track[-1] if track else None


def line_weights(t_s: NDArray[np.float64], t: float, omega: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Weights w_i of the least-squares line through samples at ``t_s`` evaluated at ``t``, each sample
    weighed by ``omega`` (None: all alike): ``sum w_i = 1``, ``sum w_i t_i = t`` (a line is reproduced
    exactly)."""
    o = np.full(len(t_s), 1.0 / len(t_s)) if omega is None else omega / omega.sum()
    mean = float(o @ t_s)
    spread = float(o @ (t_s - mean) ** 2)
    return o + o * (t_s - mean) * (t - mean) / spread


def _line(track: list[Sample], t_us: int, lever_m: float) -> Aligned | None:
    """The least-squares line through ``track`` at ``t_us``, with its covariance (see the module)."""
    ref = track[-1]
    t_s = np.array([(s.t_us - ref.t_us) / 1e6 for s in track])
    if float(np.ptp(t_s)) <= 0.0:
        return None
    t = (t_us - ref.t_us) / 1e6
    # Each sample weighed by the inverse of the variance it would give the child (its position's
    # and its attitude's over the lever arm): a frame its own covariance says is poor counts less.
    var = np.array([np.trace(s.cov[:3, :3]) + lever_m**2 * np.trace(s.cov[3:, 3:]) for s in track])
    w = line_weights(t_s, t, 1.0 / var if bool(np.all(var > 0.0)) else None)
    p = np.einsum("i,ij->j", w, np.array([s.p for s in track]))
    R_ref = Rotation.from_quat(ref.q)
    # Rotation vectors about the newest attitude's axes (the covariance's convention: body axes).
    theta = (R_ref.inv() * Rotation.from_quat(np.array([s.q for s in track]))).as_rotvec()
    q = (R_ref * Rotation.from_rotvec(w @ theta)).as_quat()
    cov = np.einsum("i,ijk->jk", w**2, np.array([s.cov for s in track]))
    # A line's miss of a path accelerating by a: a / 2 * sum w_i (t_i - t)^2, per axis.
    reach = 0.5 * abs(float(w @ (t_s - t) ** 2))
    idx = np.arange(3)
    cov[idx, idx] += (ACCEL_SIGMA_M_S2 * reach) ** 2
    cov[idx + 3, idx + 3] += (ANGULAR_ACCEL_SIGMA_RAD_S2 * reach) ** 2
    return Aligned(p, q, cov)
