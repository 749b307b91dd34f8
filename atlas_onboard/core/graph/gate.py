"""Beyond the paper: the consensus gate, which leaves out a candidate that contradicts the others.

A candidate that rests on peers' work (anything but the node's own cameras' direct views of the
frame's root) is first held to the speed bound: it may not place its entity farther from the entity's
last estimate than that estimate's uncertainty and the vehicle's top speed allow (:meth:`ConsensusGate.keep`).
Then a candidate is judged against the node's own cameras' views (the anchor, which no peer outvotes),
then against the consensus of its entity's candidates or, with fewer than three, the entity's last
estimate (a :class:`PriorEstimate`), allowing for what the entity may have moved meanwhile.

The uncertainty a candidate is judged with is the one it is weighed with: its covariance, with the
observation's part shrunk where the sigma it is weighed by claims more confidence (see
:class:`GateInput`), so that a large covariance cannot widen the gate of a heavily weighed candidate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core.graph.edges import EdgeKey

MAX_SPEED_M_S = 3.0
"""The outlier gate's allowance for motion since the last estimate (an indoor drone's top speed)."""
MAX_RATE_RAD_S = 3.0
"""And for rotation since the last estimate (about 170 deg/s)."""
SPEED_GATE_SIGMA = 5.0
"""The speed bound's allowance for the estimates' errors, in their standard deviations, when the
consensus gate is off (otherwise the gate's own ``k_sigma``)."""
SPEED_CANDIDATE_SIGMA_CAP_M = 0.1
"""A candidate's own uncertainty widens the speed bound by at most this (position, 1 sigma): a view
less precise than 10 cm would barely move a fused pose by its weight, and a sender's large covariance
must not open the bound to anywhere (a candidate 20 m off with a covariance that covers 20 m)."""
SPEED_CANDIDATE_SIGMA_CAP_RAD = 0.1
"""The same for the attitude (about 6 degrees, 1 sigma)."""


class PriorEstimate(NamedTuple):
    """An entity's last fused estimate in one frame: the gate's reference when it has fewer than
    three candidates, and what it keeps when the gate leaves out every candidate.

    Attributes:
        p_m: position in the frame's root, metres, shape (3,).
        q_xyzw: orientation in the frame's root, x-first, shape (4,).
        sigma_m: standard deviation of the position, metres.
        sigma_att_rad: standard deviation of the attitude (mean of its three axes), radians.
        made_ns: when it was made, on the evaluation's clock (ns): when a candidate was last
            accepted for the entity (a refused one changes nothing, so the bounds it sets grow with
            the time since).
        capture_time_us: capture time of its newest observation, on the swarm's clock (us).
        cov_sigma_m: standard deviation of the position from its 6x6 covariance (mean of the three
            axes), metres (the speed bound takes the larger of this and ``sigma_m``).
    """

    p_m: NDArray[np.float64]
    q_xyzw: NDArray[np.float64]
    sigma_m: float
    sigma_att_rad: float
    made_ns: int
    capture_time_us: int
    cov_sigma_m: float = 0.0


@dataclass(slots=True)
class GateInput:
    """One stage's candidates as the gate sees them, shapes (N, ...): ``child`` (entity index),
    ``p``, ``q`` (xyzw) and ``cov`` (6x6) of each candidate in the root's frame, ``capture_us``
    (capture time of its newest part), ``anchored`` (the own cameras' direct views of the root's
    markers), ``arrival_ns`` (when its edge arrived). ``cov`` is the covariance the candidate is
    weighed with: where the sigma its fusion weight comes from claims more confidence than the
    covariance, the covariance is shrunk to it (:func:`atlas_onboard.core.graph.candidates.gate_covariance`)."""

    child: NDArray[np.intp]
    p: NDArray[np.float64]
    q: NDArray[np.float64]
    cov: NDArray[np.float64]
    capture_us: NDArray[np.int64]
    anchored: NDArray[np.bool_]
    arrival_ns: NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class Verdict:
    """The gate's verdict on a stage's candidates, shape (N,): ``keep``, and among those left out the
    ones the speed bound refused (``too_fast``; the others contradicted the anchor or the consensus)."""

    keep: NDArray[np.bool_]
    too_fast: NDArray[np.bool_]


class ConsensusGate:
    """The gate of one graph, with its memory: each entity's last estimate per frame root, and
    which edge observations it has already counted as rejected."""

    def __init__(self, k_sigma: float, edge_timeout_ns: int, max_speed_m_s: float = 0.0) -> None:
        self.k_sigma = k_sigma  # a candidate beyond this many standard deviations is out; 0: off
        self.edge_timeout_ns = edge_timeout_ns
        self.max_speed_m_s = max_speed_m_s  # the speed bound on peers' candidates; 0: off
        self.priors: dict[tuple[int, int], PriorEstimate] = {}  # (root, entity) -> its last estimate
        self._counted: dict[EdgeKey, int] = {}  # edge -> the arrival stamp of its last counted rejection
        self._counted_before: dict[EdgeKey, int] = {}  # and the one before (a record put back)
        self.rejected_total = 0  # distinct edge observations rejected (each counted once)
        self.too_fast_total = 0  # of those, refused by the speed bound

    @property
    def enabled(self) -> bool:
        return self.k_sigma > 0.0 or self.max_speed_m_s > 0.0

    def count(self, keys: list[EdgeKey | None], stamps_ns: list[int], too_fast: bool = False) -> None:
        """Count the rejected observations (edge and arrival stamp) not counted before; ``too_fast``:
        those the speed bound refused (counted apart)."""
        last, before = self._counted, self._counted_before
        for key, stamp in zip(keys, stamps_ns, strict=True):
            if key is not None and stamp not in (last.get(key), before.get(key)):
                if key in last:
                    before[key] = last[key]
                last[key] = stamp
                if too_fast:
                    self.too_fast_total += 1
                else:
                    self.rejected_total += 1

    def remember(self, root: int, entity: int, prior: PriorEstimate) -> None:
        self.priors[(root, entity)] = prior

    def verdict(self, root: int, now_ns: int, c: GateInput) -> Verdict:
        """The speed bound (:meth:`too_fast`), then the consensus (:meth:`keep`) on what it kept."""
        fast = self.too_fast(root, now_ns, c)
        if self.k_sigma <= 0.0:
            return Verdict(~fast, fast)
        if not fast.any():
            return Verdict(self.keep(root, now_ns, c), fast)
        rest = np.flatnonzero(~fast)
        keep = np.zeros(len(fast), dtype=bool)
        sub = GateInput(c.child[rest], c.p[rest], c.q[rest], c.cov[rest], c.capture_us[rest], c.anchored[rest],
                        c.arrival_ns[rest])  # fmt: skip
        keep[rest] = self.keep(root, now_ns, sub)
        return Verdict(keep, fast)

    def too_fast(self, root: int, now_ns: int, c: GateInput) -> NDArray[np.bool_]:
        """Which candidates resting on peers' work (not ``anchored``) would move their entity beyond
        what its last estimate allows, each on its own (before any consensus: several forged views
        cannot outvote the real one by their number).

        The bound on the position is ``k (sigma_prior (+) sigma_candidate) + max_speed * dt``: the
        estimate's uncertainty (the larger of its scalar and covariance sigmas) and the candidate's
        (at most ``SPEED_CANDIDATE_SIGMA_CAP_M``) combined, plus the distance the vehicle can cover in
        the time ``dt`` from the estimate's capture to the candidate's (0 for a candidate older than
        the estimate: a sender chooses its stamps, and an old stamp must not buy distance). The
        attitude likewise, with ``MAX_RATE_RAD_S``. No bound without an estimate. A loss (nothing accepted
        for the edge timeout) does not lift it: the vehicle can still have moved only so far, and a bound
        lifted whenever the real views are late (a loaded computer, a lossy link) would hand the
        re-acquisition to whatever forged views outnumber them. It widens with the time since instead,
        so a real re-acquisition after a long loss is taken. ``k`` is the gate's ``k_sigma``, or
        ``SPEED_GATE_SIGMA`` when the gate is off. All False when the bound is off."""
        fast = np.zeros(len(c.child), dtype=bool)
        if self.max_speed_m_s <= 0.0:
            return fast
        k = self.k_sigma if self.k_sigma > 0.0 else SPEED_GATE_SIGMA
        peers = np.flatnonzero(~c.anchored)
        if peers.size == 0:
            return fast
        cov = c.cov[peers]
        s_pos = np.minimum(np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2) / 3.0), SPEED_CANDIDATE_SIGMA_CAP_M)
        s_att = np.minimum(np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2) / 3.0), SPEED_CANDIDATE_SIGMA_CAP_RAD)
        for j, i in enumerate(peers.tolist()):
            prior = self.priors.get((root, int(c.child[i])))
            if prior is None:
                continue
            dt_s = max(int(c.capture_us[i]) - prior.capture_time_us, 0) / 1e6
            sp = max(prior.sigma_m, prior.cov_sigma_m)
            d_p = float(np.linalg.norm(c.p[i] - prior.p_m))
            d_a = float(angles(prior.q_xyzw, c.q[i]))
            ok = (
                d_p <= k * np.hypot(sp, s_pos[j]) + self.max_speed_m_s * dt_s
                and d_a <= k * np.hypot(prior.sigma_att_rad, s_att[j]) + MAX_RATE_RAD_S * dt_s
            )
            fast[i] = not ok
        return fast

    def keep(self, root: int, now_ns: int, c: GateInput) -> NDArray[np.bool_]:
        """Which candidates agree with the consensus of their entity's candidates.

        First, where some of an entity's candidates are direct views of the root's markers by the
        node's own sensors (``anchored``), those are the anchor: any other candidate (a peer's,
        whoever sent it) that agrees with none of them within ``k_sigma`` standard deviations (both
        candidates', plus what the entity may have moved between their captures, at most between
        their arrivals: a sender chooses its stamps, not when they arrive) is out, however many such
        candidates there are and however small their sigma. The rest are then judged among
        themselves as follows.

        With three or more candidates the reference is their median (position per axis; orientation:
        the candidate nearest to all others), which one wrong candidate cannot move. With fewer, the
        reference is the entity's last estimate if it is younger than the edge timeout, widened by
        what the entity may have moved since (since the estimate was made or since the capture of
        its newest observation against the estimate's, whichever is longer: an estimate made a
        moment ago may rest on a frame taken well before). A candidate is out when its position or
        attitude is more than ``k_sigma`` standard deviations (its own and the reference's) away.
        If the median would leave out more than half of the candidates, there is no consensus and
        all are kept; two candidates that both contradict the last estimate but agree with each other
        are kept (the estimate is out of date). A lone candidate against a fresh estimate loses: the
        entity keeps its estimate until that is older than the edge timeout.
        """
        k = self.k_sigma
        child, p, q, cov = c.child, c.p, c.q, c.cov
        keep = np.ones(len(child), dtype=bool)
        s_pos = np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2) / 3.0)
        s_att = np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2) / 3.0)
        for v in np.unique(child):
            idx = np.flatnonzero(child == v)
            own = c.anchored[idx]
            if own.any() and not own.all():
                agree = self._agrees_with_anchor(idx[~own], idx[own], c, s_pos, s_att)
                keep[idx[~own][~agree]] = False
                idx = idx[own | np.isin(idx, idx[~own][agree])]
            q_v = q[idx]
            if len(idx) >= 3:
                ref_p = _median_rows(p[idx])
                ref_q = q_v[int(np.argmin(angles(q_v[:, None, :], q_v[None, :, :]).sum(axis=1)))]
                ref_s, ref_a, slack_p, slack_a = 0.0, 0.0, 0.0, 0.0
            else:
                prior = self.priors.get((root, int(v)))
                if prior is None or now_ns - prior.made_ns > self.edge_timeout_ns:
                    continue
                # The swarm's capture clock and the evaluation's clock are not compared, only their gaps.
                age_s = np.maximum((now_ns - prior.made_ns) / 1e9, (c.capture_us[idx] - prior.capture_time_us) / 1e6)
                ref_p, ref_q, ref_s, ref_a = prior.p_m, prior.q_xyzw, prior.sigma_m, prior.sigma_att_rad
                slack_p, slack_a = MAX_SPEED_M_S * age_s, MAX_RATE_RAD_S * age_s
            d_p = np.linalg.norm(p[idx] - ref_p, axis=1)
            d_a = angles(ref_q, q_v)
            ok = (d_p <= k * np.hypot(s_pos[idx], ref_s) + slack_p) & (d_a <= k * np.hypot(s_att[idx], ref_a) + slack_a)
            if len(idx) >= 3:
                if ok.sum() * 2 >= len(idx):
                    keep[idx] = ok
            elif len(idx) == 2 and not ok.any():
                # Both contradict the last estimate: if they agree with each other, it is the estimate
                # that is out of date (kept both); if not, nothing can be trusted (both out).
                d2 = float(np.linalg.norm(p[idx[0]] - p[idx[1]]))
                a2 = float(angles(q_v[0], q_v[1]))
                agree = d2 <= k * np.hypot(s_pos[idx[0]], s_pos[idx[1]]) and a2 <= k * np.hypot(*s_att[idx])
                keep[idx] = agree
            else:
                keep[idx] = ok
        return keep

    def _agrees_with_anchor(
        self,
        others: NDArray[np.intp],
        anchors: NDArray[np.intp],
        c: GateInput,
        s_pos: NDArray[np.float64],
        s_att: NDArray[np.float64],
    ) -> NDArray[np.bool_]:
        """For each of ``others``: whether it is within the gate of at least one of ``anchors``."""
        k = self.k_sigma
        p, q, capture_us, arrival_ns = c.p, c.q, c.capture_us, c.arrival_ns
        d_p = np.linalg.norm(p[others][:, None, :] - p[anchors][None, :, :], axis=2)  # (others, anchors)
        d_a = angles(q[others][:, None, :], q[anchors][None, :, :])
        dt_capture_s = np.abs(capture_us[others][:, None] - capture_us[anchors][None, :]) / 1e6
        dt_arrival_s = np.abs(arrival_ns[others][:, None] - arrival_ns[anchors][None, :]) / 1e9
        dt_s = np.minimum(dt_capture_s, dt_arrival_s)
        ok_p = d_p <= k * np.hypot(s_pos[others][:, None], s_pos[anchors][None, :]) + MAX_SPEED_M_S * dt_s
        ok_a = d_a <= k * np.hypot(s_att[others][:, None], s_att[anchors][None, :]) + MAX_RATE_RAD_S * dt_s
        return np.asarray((ok_p & ok_a).any(axis=1))


def _median_rows(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``np.median(x, axis=0)`` of an (n, k) array, n >= 1, bit for bit: the middle row of the sorted
    columns, or the mean of the two middle ones (a sort costs a fraction of np.median on the gate's
    few candidates); np.median itself where a value is not finite (its NaN rule)."""
    if not np.isfinite(x).all():
        return np.median(x, axis=0)
    s = np.sort(x, axis=0)
    m = len(s) // 2
    return s[m] if len(s) % 2 else (s[m - 1] + s[m]) / 2.0


def angles(q_a_xyzw: NDArray[np.float64], q_b_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation angle (rad) between unit quaternions, broadcast over leading axes: what
    ``(Rotation.from_quat(a).inv() * Rotation.from_quat(b)).magnitude()`` gives, for the gate's many
    small sets without building Rotation objects (2 acos |a . b|, either sign of a quaternion)."""
    dot = np.abs(np.sum(np.asarray(q_a_xyzw) * np.asarray(q_b_xyzw), axis=-1))
    return 2.0 * np.arccos(np.minimum(dot, 1.0))
