"""Cooperative localisation at its physical floor: the relay-follow scenario, live camera path.

A leader flies a figure-eight over floor tags (with short stretches of none); a follower 1.2-2.5 m
behind it sees only the 20 cm tag on the leader's back. Each run is ``atlas-onboard sim --scenario
relay-follow`` in this process (the cameras' images rendered once and reused by every run): two real
node processes, the real detector on rendered images, simulated autopilots, real MAVLink over
loopback. Scored against ground truth from what each autopilot received, at each message's capture
time:

- the follower's position error: median, mean, RMSE, p95, max; the share of messages within 3 sigma
  per axis (x y z of local NED) and on all three at once; pose NEES (about 6 when honest);
- during the leader's gaps (frames in which the leader sees no tag fully): the follower's messages,
  their largest error, and how many are farther than 3 sigma on some axis;
- the leader's figures.

The anchor is the per-frame floor: the follower's own one-tag PnP of each of its frames (the node's
detector, same settings, frames in order) composed with the leader's *true* pose at that frame's
capture time: what the follower's view allows. ``--offline`` adds the estimator alone (no processes,
no load: each camera's frames at its own rate, observations arriving 20 ms after capture) beside
the live runs.

    python benchmarks/bench_relay.py [--duration 30] [--runs defaults,ekf,paper] [--offline] [--no-live]

Run it on an otherwise idle machine with a core for each node, as each drone has its own computer: the
nodes must keep up with their cameras in real time (the frames they skipped are printed; pinned to one
core, ``taskset -c 1``, the two nodes share it and the leader skips frames). ``--offline`` alone
(``--no-live``) may be pinned: it measures no time.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.markerdata import Rejection
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.listener import Listener
from atlas_onboard.node.setup import make_graph
from atlas_onboard.sim import follow, report, runner, scenarios
from atlas_onboard.sim.camera import frames_path
from atlas_onboard.sim.command import score_run
from atlas_onboard.sim.runner import WARMUP_S, SimOptions, run
from atlas_onboard.sim.world import SimWorld

SCENARIO = "relay-follow"
LEADER, FOLLOWER = "leader", "follower"
RUNS: dict[str, dict[str, Any]] = {"defaults": {}, "ekf": {"filter": "ekf"}, "paper": {"method": "paper"}}
DEFAULT_RUNS = ("defaults", "ekf")
OFFLINE_DELAY_S = 0.02
# (key, unit, limit, op, against the floor)
BARS = (
    ("median_over_floor", "x", 1.5, "<="),
    ("rmse_over_floor", "x", 2.0, "<="),
    ("max", "mm", 60.0, "<="),
    ("within3_min", "%", 99.0, ">="),
    ("within3_all", "%", 98.5, ">="),
    ("nees6_low", "", 3.0, ">="),
    ("nees6_high", "", 9.0, "<="),
    ("gap_over_3sigma", "count", 0, "<="),
)


@dataclass
class Figures:
    """One estimate's errors against truth: position error (mm) per message, and where known the
    errors and covariances in the published frame."""

    err_mm: NDArray[np.float64]
    e6: NDArray[np.float64] | None = None  # (N, 6)
    cov: NDArray[np.float64] | None = None  # (N, 6, 6)
    in_gap: NDArray[np.bool_] | None = None

    def summary(self) -> dict[str, float]:
        e = self.err_mm
        out: dict[str, float] = {"messages": float(len(e))}
        if not len(e):
            return out
        out.update(median=float(np.median(e)), mean=float(e.mean()), rmse=float(np.sqrt(np.mean(e**2))))
        out.update(p95=float(np.percentile(e, 95)), max=float(e.max()))
        if self.e6 is not None and self.cov is not None:
            sd = np.sqrt(np.diagonal(self.cov[:, :3, :3], axis1=1, axis2=2))
            inside = np.abs(self.e6[:, :3]) <= 3.0 * sd
            wx, wy, wz = (float(v) * 100 for v in inside.mean(axis=0))
            out.update(within3_x=wx, within3_y=wy, within3_z=wz, within3_min=min(wx, wy, wz))
            out["within3_all"] = float(inside.all(axis=1).mean() * 100)
            nees = report.nees(self.e6, self.cov)
            out["nees6"] = float(np.nanmean(nees))
            out["nees3"] = float(np.nanmean(report.nees(self.e6[:, :3], self.cov[:, :3, :3])))
            if self.in_gap is not None:
                g = self.in_gap
                out["gap_messages"] = float(g.sum())
                out["gap_max"] = float(e[g].max()) if g.any() else math.nan
                out["gap_over_3sigma"] = float((~inside[g].all(axis=1)).sum())
        return out


@dataclass
class Result:
    name: str
    follower: dict[str, float] = field(default_factory=dict)
    leader: dict[str, float] = field(default_factory=dict)
    skipped: str = ""
    counters: dict[str, int] = field(default_factory=dict)
    error: str = ""


def leader_gaps(world: SimWorld, t1_s: float) -> NDArray[np.float64]:
    """(K, 2) stretches in which the leader saw no tag fully (between two frames that did, more than a
    frame and a half apart), in seconds from the start."""
    seen = world.visible_frames(LEADER, t1_s)
    period = world.frame_period_s()
    d = np.diff(seen)
    at = np.flatnonzero(d > 1.5 * period)
    return np.column_stack([seen[at], seen[at + 1]]) if len(at) else np.zeros((0, 2))


def inside(t_s: NDArray[np.float64], gaps: NDArray[np.float64]) -> NDArray[np.bool_]:
    return np.any((t_s[:, None] > gaps[None, :, 0]) & (t_s[:, None] < gaps[None, :, 1]), axis=1)


def run_one(name: str, duration_s: float) -> Result:
    res = Result(name)
    overrides = {"fusion": dict(RUNS[name])} if RUNS[name] else {}
    try:
        sim = run(SimOptions(scenario=SCENARIO, duration_s=duration_s, world_overrides=overrides))
    except Exception as exc:  # a run that fails is a row that says so, not the end of the benchmark
        res.error = f"{type(exc).__name__}: {exc}"
        return res
    _rep, tracks = score_run(sim)
    gaps = leader_gaps(sim.world, sim.duration_s)
    for entity in (LEADER, FOLLOWER):
        track = tracks[entity]
        sel = (track.arrival_s >= WARMUP_S) & (track.arrival_s <= sim.duration_s)
        cap = track.capture_s[sel]
        p_true, q_true = sim.world.truth_series(entity, cap)
        err = np.linalg.norm(track.p_m[sel] - p_true, axis=1) * 1e3
        figs = Figures(err)
        if track.p_ned_m is not None and track.q_ned_frd_xyzw is not None and track.covariance_ned_frd is not None:
            e6 = report.pose_errors_ned_frd(track.p_ned_m[sel], track.q_ned_frd_xyzw[sel], p_true, q_true)
            figs = Figures(err, e6, track.covariance_ned_frd[sel], inside(cap, gaps))
        setattr(res, entity, figs.summary())
    skipped = []
    for entity in (LEADER, FOLLOWER):
        log = sim.logs.get(entity, "").splitlines()
        final = next((line for line in reversed(log) if " final " in line), "")
        counters = {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", final)}
        cams = {k: v for k, v in counters.items() if k.startswith("camera_") and "_detector_" not in k}
        frames = sum(v for k, v in cams.items() if k.endswith("_frames"))
        skip = sum(v for k, v in cams.items() if k.endswith(("_frames_skipped", "_frames_dropped")))
        skipped.append(f"{skip}/{frames + skip}")
        if entity == FOLLOWER:
            about = r"ambiguity|attitude_(alt|both|neither|primary)|rejected"
            res.counters = {k: v for k, v in counters.items() if re.search(about, k)}
    res.skipped = " ".join(skipped)
    return res


@dataclass
class Camera:
    sensor: Any
    detector: Detector
    frames: Any
    fps: float


def cameras(world_cfg: Any, sim_world: SimWorld, directory: Path) -> dict[str, Camera]:
    out = {}
    for sid, (sensor, intr) in sim_world.cameras.items():
        frames = np.load(frames_path(directory, sid), mmap_mode="r")
        fps = sensor.camera.fps if sensor.camera and sensor.camera.fps > 0 else 30.0
        out[sensor.entity] = Camera(sensor, Detector(sensor, world_cfg, intr.calibration(), decimate=2.0), frames, fps)
    return out


def per_frame_floor(duration_s: float, directory: Path) -> Figures:
    """The follower's own one-tag PnP of each frame (the node's detector, frames in order; eq. 1 by the
    listener with no estimate, no refusal) composed with the leader's true pose at the capture time."""
    scenario = scenarios.get(SCENARIO)
    world = scenario.world()
    sim_world = SimWorld(scenario)
    cam = cameras(world, sim_world, directory)[FOLLOWER]
    listener = Listener(world, make_graph(world, FOLLOWER), ambiguity_threshold=1.0)
    errors = []
    for j in range(math.ceil(WARMUP_S * cam.fps), min(len(cam.frames), math.floor(duration_s * cam.fps))):
        t = j / cam.fps
        truth = sim_world.truth(t, (LEADER, FOLLOWER))
        for md in cam.detector.detect(np.asarray(cam.frames[j]), round(t * 1e6)):
            edge = listener.edge_from(md)
            if isinstance(edge, Rejection) or edge.observer != FOLLOWER or edge.observed != LEADER:
                continue
            T_fl = RigidTransform.from_components(edge.p_a_b, Rotation.from_quat(edge.q_a_b_xyzw))
            T_wf = truth[LEADER] * T_fl.inv()
            errors.append(float(np.linalg.norm(T_wf.translation - truth[FOLLOWER].translation)) * 1e3)
    return Figures(np.array(errors))


def offline(duration_s: float, directory: Path, fusion: dict[str, Any]) -> dict[str, float]:
    """The follower's estimator alone on the run's frames (:mod:`atlas_onboard.sim.follow`): each camera
    at its own rate, every observation arriving ``OFFLINE_DELAY_S`` after its capture, the follower's
    autopilot attitude as the simulated autopilot measures it (the live node's gravity)."""

    def frames_of(sid: int) -> Any:
        frames = np.load(frames_path(directory, sid), mmap_mode="r")
        return lambda j: frames[j]

    up_at = follow.autopilot_up(SimWorld(scenarios.get(SCENARIO)), FOLLOWER)
    track = follow.run(SCENARIO, FOLLOWER, frames_of, WARMUP_S, duration_s, OFFLINE_DELAY_S, fusion, up_at=up_at)
    if not len(track.capture_s):
        return {"messages": 0.0}
    gaps = leader_gaps(SimWorld(scenarios.get(SCENARIO)), duration_s)
    in_gap = inside(track.capture_s, gaps)
    return Figures(track.error_mm, track.errors, track.covariances, in_gap).summary()


def bar_values(f: dict[str, float], floor: dict[str, float]) -> dict[str, float]:
    get = lambda k: f.get(k, math.nan)  # noqa: E731
    return {
        "median_over_floor": get("median") / floor.get("median", math.nan),
        "rmse_over_floor": get("rmse") / floor.get("rmse", math.nan),
        "max": get("max"),
        "within3_min": get("within3_min"),
        "within3_all": get("within3_all"),
        "nees6_low": get("nees6"),
        "nees6_high": get("nees6"),
        "gap_over_3sigma": get("gap_over_3sigma"),
    }


def row(name: str, f: dict[str, float], extra: str = "") -> str:
    g = lambda k: f.get(k, math.nan)  # noqa: E731
    return (
        f"{name:<24} {g('messages'):>5.0f} {g('median'):>7.2f} {g('mean'):>7.2f} {g('rmse'):>7.2f} {g('p95'):>7.2f}"
        f" {g('max'):>7.1f} {g('within3_x'):>6.1f} {g('within3_y'):>6.1f} {g('within3_z'):>6.1f}"
        f" {g('within3_all'):>6.1f} {g('nees3'):>6.2f} {g('nees6'):>6.2f} {g('gap_messages'):>5.0f}"
        f" {g('gap_max'):>7.1f} {g('gap_over_3sigma'):>5.0f}  {extra}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=30.0, help="seconds per run (default 30)")
    ap.add_argument("--runs", default=",".join(DEFAULT_RUNS), help=f"comma-separated, from {', '.join(RUNS)}")
    ap.add_argument("--offline", action="store_true", help="also the estimator alone on the same frames")
    ap.add_argument("--no-live", action="store_true", help="no node processes: the floor and --offline only")
    args = ap.parse_args(argv)
    names = [n for n in args.runs.split(",") if n]
    unknown = [n for n in names if n not in RUNS]
    if unknown:
        print(f"bench_relay: unknown run(s) {', '.join(unknown)} (choose from {', '.join(RUNS)})", file=sys.stderr)
        return 2
    print(f"rendering {SCENARIO} ...", file=sys.stderr, flush=True)
    directory = runner._rendered_frames(scenarios.get(SCENARIO), 0, args.duration, lambda _m: None)
    assert directory is not None
    results = []
    for i, name in enumerate([] if args.no_live else names, start=1):
        print(f"[{i}/{len(names)}] {name} ...", file=sys.stderr, flush=True)
        results.append(run_one(name, args.duration))
    print("per-frame floor ...", file=sys.stderr, flush=True)
    floor = per_frame_floor(args.duration, directory).summary()
    offline_rows = {}
    if args.offline:
        for name in names:
            print(f"offline {name} ...", file=sys.stderr, flush=True)
            offline_rows[name] = offline(args.duration, directory, RUNS[name])
    print(f"scenario {SCENARIO}: {scenarios.get(SCENARIO).description}")
    print(f"{args.duration:g} s per run, scored from {WARMUP_S:g} s; anchor: the per-frame floor (the follower's")
    print("one-tag view of each frame composed with the leader's true pose), on the same frames; errors in mm")
    head = (
        f"{'':<24} {'msgs':>5} {'median':>7} {'mean':>7} {'RMSE':>7} {'p95':>7} {'max':>7} {'3s x%':>6} {'3s y%':>6}"
        f" {'3s z%':>6} {'3s xyz':>6} {'NEES3':>6} {'NEES6':>6} {'gap n':>5} {'gapmax':>7} {'>3s':>5}"
    )
    print(head)
    print(row("floor (per frame)", floor, "(detections, not messages)"))
    for r in results:
        if r.error:
            print(f"{r.name:<24} failed: {r.error}")
            continue
        print(row(f"follower {r.name}", r.follower, f"skipped frames leader/follower {r.skipped}"))
        if r.name in offline_rows:
            print(row(f"  offline {r.name}", offline_rows[r.name]))
    for name, f in offline_rows.items():
        if all(r.name != name or r.error for r in results):
            print(row(f"  offline {name}", f))
    print()
    print("the leader (what its autopilot received)")
    print(head)
    for r in results:
        if not r.error:
            print(row(f"leader {r.name}", r.leader))
    print()
    for r in results:
        if not r.error:
            print(f"follower {r.name} counters: {r.counters or 'none'}")
    print()
    rows = [(r.name, {} if r.error else r.follower) for r in results]
    rows += [(f"offline-{name}", f) for name, f in offline_rows.items()]  # the estimator alone
    for name, follower in rows:
        values = bar_values(follower, floor) if follower else {}
        for key, unit, limit, op in BARS:
            value = values.get(key, math.nan)
            ok = math.isfinite(value) and ((value <= limit) if op == "<=" else (value >= limit))
            print(f"BAR {name}.{key} {value:.4g} {unit or '-'} {limit:g} {'pass' if ok else 'fail'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
