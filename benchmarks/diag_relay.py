"""Where the follower's error above the per-frame floor comes from, per published pose (relay-follow,
the estimator alone on the rendered frames as ``bench_relay --offline`` runs it).

Each published follower pose rests on candidates through the leader: the leader's pose taken at the
follower's capture time (the parent) composed with the follower's view of the leader's tag (the edge).
For each, against truth at that capture time:

- ``floor``: the edge composed with the leader's *true* pose (what bench_relay's floor measures);
- ``leader``: the true edge composed with the leader's estimated pose (the parent's share), split into
  its position error and its attitude error swung over the lever arm;
- ``flip``: the edge's attitude error above ``FLIP_DEG`` (the tag's other IPPE solution);
- ``fused``: what was published;
- the leader at its own instants (error, NEES), the line through its true poses (the interpolation's own
  miss), and the follower had the leader been interpolated otherwise.

    python benchmarks/diag_relay.py [--duration 20]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.graph.timing import MotionHistory, Sample
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.listener import Listener
from atlas_onboard.node.setup import make_graph
from atlas_onboard.sim import runner, scenarios
from atlas_onboard.sim.camera import frames_path
from atlas_onboard.sim.runner import WARMUP_S
from atlas_onboard.sim.world import SimWorld

SCENARIO, LEADER, FOLLOWER = "relay-follow", "leader", "follower"
DELAY_S = 0.02
FLIP_DEG = 3.0


def stats(name: str, x: np.ndarray) -> str:
    if not len(x):
        return f"{name:<40} none"
    return (
        f"{name:<40} n {len(x):>5} median {np.median(x):7.2f} mean {x.mean():7.2f} rms {np.sqrt(np.mean(x**2)):7.2f}"
        f" p95 {np.percentile(x, 95):7.2f} max {x.max():7.2f}"
    )


def lagrange(ts: np.ndarray, t: float) -> np.ndarray:
    w = np.ones(len(ts))
    for i in range(len(ts)):
        for j in range(len(ts)):
            if i != j:
                w[i] *= (t - ts[j]) / (ts[i] - ts[j])
    return w


def interpolations(track: list[Sample], t_us: int) -> dict[str, RigidTransform]:
    ts = np.array([s.t_us for s in track], dtype=float) / 1e6
    t = t_us / 1e6
    ref = Rotation.from_quat(track[-1].q)
    theta = (ref.inv() * Rotation.from_quat(np.array([s.q for s in track]))).as_rotvec()
    P = np.array([s.p for s in track])
    # the samples bracketing t
    k = int(np.searchsorted(ts, t))
    k = min(max(k, 1), len(ts) - 1)
    out = {}

    def make(idx: list[int]) -> RigidTransform:
        idx = [i for i in idx if 0 <= i < len(ts)]
        w = lagrange(ts[idx], t)
        return RigidTransform.from_components(w @ P[idx], ref * Rotation.from_rotvec(w @ theta[idx]))

    out["line n=2"] = make([k - 1, k])
    out["lagrange n=3"] = make([k - 2, k - 1, k] if k + 1 >= len(ts) else [k - 1, k, k + 1])
    out["lagrange n=4"] = make([k - 2, k - 1, k, k + 1] if k + 1 < len(ts) else [k - 3, k - 2, k - 1, k])
    near = k if abs(ts[k] - t) < abs(ts[k - 1] - t) else k - 1
    out["nearest"] = make([near])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--set", action="append", default=[], help="fusion KEY=VALUE")
    ap.add_argument("--leader-delay-ms", type=float, default=0.0, help="the leader's poses arrive this much later")
    ap.add_argument("--frames", type=Path, help="keep the rendered frames here and reuse them")
    args = ap.parse_args(argv)
    scenario = scenarios.get(SCENARIO)
    if args.frames is not None and any(args.frames.glob("*.npy")):
        directory = args.frames
    else:
        directory = runner._rendered_frames(scenario, 0, args.duration, lambda _m: None)
        assert directory is not None
        if args.frames is not None:
            shutil.copytree(directory, args.frames, dirs_exist_ok=True)
    world = scenario.world()
    over = {k: type(getattr(world.fusion, k))(v) for k, v in (s.split("=", 1) for s in args.set)}
    world = dataclasses.replace(world, fusion=dataclasses.replace(world.fusion, **over))
    sim = SimWorld(scenario, world)
    events = []
    for sid, (sensor, intr) in sorted(sim.cameras.items()):
        fps = sensor.camera.fps if sensor.camera and sensor.camera.fps > 0 else 30.0
        det = Detector(sensor, world, intr.calibration(), decimate=2.0)
        frames = np.load(frames_path(directory, sid), mmap_mode="r")
        for j in range(max(math.floor((WARMUP_S - 0.5) * fps), 0), math.floor(args.duration * fps)):
            t = j / fps
            late = args.leader_delay_ms / 1e3 if sensor.entity == LEADER else 0.0
            events.append((t + DELAY_S + late, sensor.entity, det.detect(np.asarray(frames[j]), round(t * 1e6))))
    events.sort(key=lambda e: e[0])
    graph = make_graph(world, FOLLOWER)
    graph.keep_candidates = True
    listener = Listener(world, graph)
    last, last_leader = -1, -1
    truth_line = MotionHistory()  # the leader's true poses at its estimates' instants and covariances
    est_line = MotionHistory()  # the leader's estimates, for other interpolations
    # the follower's error had the leader been interpolated otherwise (lines through the bracketing poses)
    alts: dict[str, list[float]] = {
        "line n=2": [],
        "lagrange n=3": [],
        "lagrange n=4": [],
        "nearest": [],
    }
    lead_own = []  # the leader's estimate at its own instants: position mm, attitude deg
    rows = []  # per published pose (see the columns printed)
    for arrival, _who, mds in events:
        now = round(arrival * 1e9)
        listener.accept_many([(md, now) for md in mds])
        result = graph.evaluate(now)
        listener.set_estimates(result.poses)
        ld = result.poses.get(LEADER)
        if ld is not None and ld.capture_time_us > last_leader and ld.covariance is not None:
            last_leader = ld.capture_time_us
            T = sim.truth(ld.capture_time_us / 1e6, (LEADER,))[LEADER]
            est_line.add(0, 0, Sample(ld.capture_time_us, ld.p_world_m.copy(), ld.q_world_xyzw.copy(), ld.covariance))
            truth_line.add(0, 0, Sample(ld.capture_time_us, T.translation, T.rotation.as_quat(), ld.covariance))
            if ld.capture_time_us / 1e6 >= WARMUP_S:
                att_err = (T.rotation.inv() * Rotation.from_quat(ld.q_world_xyzw)).magnitude()
                e6 = np.r_[
                    ld.p_world_m - T.translation, (T.rotation.inv() * Rotation.from_quat(ld.q_world_xyzw)).as_rotvec()
                ]
                nees_att = float(e6[3:] @ np.linalg.solve(ld.covariance[3:, 3:], e6[3:]))
                nees6 = float(e6 @ np.linalg.solve(ld.covariance, e6))
                lead_own.append(
                    (np.linalg.norm(ld.p_world_m - T.translation) * 1e3, np.degrees(att_err), nees6, nees_att)
                )
        f = result.poses.get(FOLLOWER)
        if f is None or f.capture_time_us <= last:
            continue
        last = f.capture_time_us
        tc = f.capture_time_us / 1e6
        if tc < WARMUP_S:
            continue
        truth = sim.truth(tc, (LEADER, FOLLOWER))
        fused = float(np.linalg.norm(f.p_world_m - truth[FOLLOWER].translation)) * 1e3
        for c in result.candidates.get(FOLLOWER, []):
            if c.parent != LEADER or c.capture_time_us != f.capture_time_us:
                continue
            T_c = RigidTransform.from_components(c.p_m, Rotation.from_quat(c.q_xyzw))
            T_e = RigidTransform.from_components(c.p_pc, Rotation.from_quat(c.q_pc))
            T_p = T_c * T_e.inv()
            T_e_true = truth[LEADER].inv() * truth[FOLLOWER]
            floor = truth[LEADER] * T_e
            lead = T_p * T_e_true
            # leader's share split: its position error, and its attitude error swung over the lever
            dp = T_p.translation - truth[LEADER].translation
            swing = lead.translation - truth[FOLLOWER].translation - dp
            att = np.degrees((truth[LEADER].rotation.inv() * T_p.rotation).magnitude())
            at = truth_line.at(0, 0, c.capture_time_us, float(np.linalg.norm(c.p_pc)))
            line_att = math.nan
            if at is not None:
                line_att = float(np.degrees((truth[LEADER].rotation.inv() * Rotation.from_quat(at.q)).magnitude()))
            track = est_line.samples(0, 0)
            if len(track) >= 4:
                for name, T_alt in interpolations(track, c.capture_time_us).items():
                    T_f = T_alt * T_e
                    alts[name].append(float(np.linalg.norm(T_f.translation - truth[FOLLOWER].translation)) * 1e3)
            e_att = np.degrees((T_e_true.rotation.inv() * T_e.rotation).magnitude())
            rows.append(
                (
                    fused,
                    float(np.linalg.norm(floor.translation - truth[FOLLOWER].translation)) * 1e3,
                    float(np.linalg.norm(dp)) * 1e3,
                    float(np.linalg.norm(swing)) * 1e3,
                    float(np.linalg.norm(lead.translation - truth[FOLLOWER].translation)) * 1e3,
                    float(e_att),
                    float(att),
                    float(np.linalg.norm(T_c.translation - truth[FOLLOWER].translation)) * 1e3,
                    line_att,
                    (c.capture_time_us - last_leader) / 1e3,
                )
            )
            break
    r = np.array(rows)
    print(f"{SCENARIO}, offline, {args.duration:g} s, scored from {WARMUP_S:g} s; mm unless said; {over or 'defaults'}")
    n_frames = sum(1 for _a, who, mds in events if who == FOLLOWER and mds and _a - DELAY_S >= WARMUP_S)
    print(f"leader's poses {args.leader_delay_ms:g} ms later than the follower's; follower frames with a detection")
    print(f"{n_frames}, poses published {len(r)}")
    print(stats("published (fused)", r[:, 0]))
    print(stats("its candidate via the leader", r[:, 7]))
    print(stats("floor: edge x true leader", r[:, 1]))
    print(stats("leader share: true edge x est leader", r[:, 4]))
    print(stats("  leader position error", r[:, 2]))
    print(stats("  leader attitude x lever", r[:, 3]))
    print(stats("  leader attitude error (deg)", r[:, 6]))
    own = np.array(lead_own)
    print(stats("  leader at its own instants, position", own[:, 0]))
    print(stats("  leader at its own instants, attitude (deg)", own[:, 1]))
    nees6, nees3 = own[:, 2], own[:, 3]
    print(f"  leader at its own instants: NEES6 mean {nees6.mean():.2f} median {np.median(nees6):.2f} (chi2: 6, 5.35)")
    print(
        f"  leader at its own instants: attitude NEES3 mean {nees3.mean():.2f} median {np.median(nees3):.2f} (3, 2.37)"
    )
    la = r[:, 8][np.isfinite(r[:, 8])]
    print(stats("  the line through its TRUE poses (deg)", la))
    print(stats("  follower capture - leader newest (ms)", r[:, 9]))
    print(stats("edge attitude error (deg)", r[:, 5]))
    for name, v in alts.items():
        print(stats(f"published if the leader were: {name}", np.array(v)))
    flip = r[:, 5] > FLIP_DEG
    print(f"edges with attitude error > {FLIP_DEG} deg (flip): {flip.sum()} of {len(r)}")
    print(stats("  published, flipped edge", r[flip, 0]))
    print(stats("  published, not flipped", r[~flip, 0]))
    print(stats("  floor, flipped edge", r[flip, 1]))
    print(stats("  floor, not flipped", r[~flip, 1]))
    ratio = float(np.median(r[:, 0]) / np.median(r[:, 1]))
    print(f"BAR follower_median_vs_floor {ratio:.3g} x 1.5 {'pass' if ratio <= 1.5 else 'fail'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
