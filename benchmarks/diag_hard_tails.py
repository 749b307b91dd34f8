"""The hard scene's tails: every fused output with a large error, what the detector saw, and its class.

Offline and deterministic: the node's detector on the scenario's pre-rendered frames in order, each
frame's MarkerData into a listener with the simulated autopilot's noisy attitude (the node's setting)
and a graph evaluated at the capture time (as :mod:`atlas_onboard.sim.offline`). For each output:
its position error, the reported sigma, and for every marker of its frame: pixel side, range, view
angle, border margin, IPPE ratio, the branch chosen vs the one nearer the truth, and the error of
each per-frame alternative (the joint solve, each marker alone on either branch, with and without
the attitude). Each output with error > ``--limit`` is classed:

- ``a``: wrong ambiguity branch (the kept single-tag edge is the branch farther from the truth, and
  the other branch is within the limit);
- ``b``: bad corners (a detection off its own 6x6 by more than the 99.9 % chi-square bound on the
  corner-driven error, with a small border margin or a large refit residual);
- ``c``: a far or grazing single tag at its honest floor (within 3.7 sigma of its own covariance);
- ``d``: the fusion chose worse than the frame's best edge (its own edge within the limit).

``e`` (EKF prediction in a gap) needs the node's filter and is not produced by this graph path.

    python benchmarks/diag_hard_tails.py [--scenario hard] [--duration 30] [--frames DIR] [--limit 30]
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_onboard.core.attitude import up_in_body
from atlas_onboard.core.markerdata import Rejection, upper_to_matrix
from atlas_onboard.detector import pose
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.refine import refine_corners_undistorted
from atlas_onboard.listener import Listener, make_graph
from atlas_onboard.sim import runner, scenarios
from atlas_onboard.sim.autopilot import SimAutopilot
from atlas_onboard.sim.camera import frames_path
from atlas_onboard.sim.world import SimWorld

ENTITY = "drone"


@dataclass
class Seen:
    """One marker of a frame: geometry against the truth and its single-tag solutions' drone errors (mm)."""

    marker_id: int
    side_px: float
    range_m: float
    view_deg: float
    margin_px: float
    ratio: float
    chosen_near: bool  # IPPE's chosen solution is the one nearer the true rotation
    err_primary_mm: float
    err_alt_mm: float
    rot_primary_deg: float
    rot_alt_deg: float
    refit_px: float


@dataclass
class Output:
    frame: int
    t_s: float
    err_mm: float
    sigma_mm: float  # sqrt of the largest eigenvalue of the published position covariance
    nees3: float
    markers: list[Seen] = field(default_factory=list)
    records: list[dict] = field(default_factory=list)  # the frame's MarkerData: id, joint, ratio, edge errors
    cls: str = ""
    view: bool = True  # a tag fully in view in this frame (the sim's visibility)


def drone_from_sensor_marker(T_world_marker, T_entity_sensor, p_sm, R_sm):  # noqa: ANN001, ANN201
    """The drone's position (world) implied by one T_sensor_marker (eq. 1 inverted)."""
    from scipy.spatial.transform import RigidTransform

    T_sm = RigidTransform.from_components(p_sm, R_sm)
    return (T_world_marker * T_sm.inv() * T_entity_sensor.inv()).translation


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="hard")
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--frames", type=Path, default=None, help="a directory of pre-rendered frames (else rendered)")
    ap.add_argument("--limit", type=float, default=30.0, help="error (mm) above which an output is a tail")
    ap.add_argument("--worst", type=int, default=50)
    ap.add_argument("--live", default="", help="also one live node run with this fusion filter (graph or ekf)")
    args = ap.parse_args()
    scenario = scenarios.get(args.scenario)
    world = scenario.world()
    sim = SimWorld(scenario)
    directory = args.frames or runner._rendered_frames(scenario, 0, args.duration, lambda _m: None)
    (sid, (sensor, intr)), = [(k, v) for k, v in sim.cameras.items() if v[0].entity == ENTITY]
    frames = np.load(frames_path(directory, sid), mmap_mode="r")
    fps = sensor.camera.fps if sensor.camera and sensor.camera.fps > 0 else 30.0
    cal = Calibration(intr.width_px, intr.height_px, intr.camera_matrix, np.asarray(intr.distortion, float))
    det = Detector(sensor, world, cal, decimate=2.0)
    W, H = intr.width_px, intr.height_px
    found_now: list = []
    inner_find = det.find

    def find(gray, R_prev_now=None):  # noqa: ANN001, ANN202
        out = inner_find(gray, R_prev_now)
        found_now[:] = out
        return out

    det.find = find  # type: ignore[method-assign]
    graph = make_graph(world, ENTITY)
    listener = Listener(world, graph)
    with_att = Listener(world, make_graph(world, ENTITY))  # per record, stateless: with the attitude
    plain = Listener(world, make_graph(world, ENTITY), ambiguity_threshold=1.0)  # the detector's choice
    ap_fields = SimAutopilot.__dataclass_fields__
    noise_rad = math.radians(ap_fields["attitude_noise_deg"].default)
    rng = np.random.default_rng(1)
    bias = rng.normal(0.0, math.radians(ap_fields["attitude_bias_deg"].default), 2)
    outputs: list[Output] = []
    in_view = set(np.round(sim.visible_frames(ENTITY, args.duration) * fps).astype(int).tolist())
    n = min(len(frames), math.floor(args.duration * fps))
    for j in range(n):
        t = j / fps
        t_us = round(t * 1e6)
        truth = sim.truth(t, (ENTITY,))[ENTITY]
        tilt = Rotation.from_rotvec(np.r_[bias + rng.normal(0.0, noise_rad, 2), 0.0])
        up = up_in_body(tilt * truth.rotation)
        for lis in (listener, with_att):
            lis.set_attitude(ENTITY, lambda _t, up=up: up)
        gray = np.asarray(frames[j])
        mds = det.detect(gray, t_us)
        T_world_sensor = truth * sensor.T_entity_sensor
        seen = []
        for d in found_now:
            if d.marker_id not in det.report.reported:
                continue
            marker = world.markers[d.marker_id]
            T_sm_true = T_world_sensor.inv() * marker.T_entity_marker
            K = cal.K
            und = pose.undistort(d.corners_px, K, cal.dist, cal.fisheye)
            ref = refine_corners_undistorted(gray, und, K, cal.dist, cal.fisheye)
            if ref is None:
                continue
            stretch = pose.undistortion_jacobian(d.corners_px, K, cal.dist, cal.fisheye)
            mp = pose.solve(ref.corners, marker.size_m, K, pose.model_sigma_px(d.family), stretch, ref.sigma_px,
                            ref.covariance)  # fmt: skip
            if mp is None:
                continue
            R_p = Rotation.from_quat(mp.q_xyzw)
            e_p = np.linalg.norm(
                drone_from_sensor_marker(marker.T_entity_marker, sensor.T_entity_sensor, mp.p_m, R_p)
                - truth.translation
            )
            rot_p = np.degrees((R_p.inv() * T_sm_true.rotation).magnitude())
            if mp.p_alt_m is not None:
                R_a = Rotation.from_quat(mp.q_alt_xyzw)
                e_a = np.linalg.norm(
                    drone_from_sensor_marker(marker.T_entity_marker, sensor.T_entity_sensor, mp.p_alt_m, R_a)
                    - truth.translation
                )
                rot_a = np.degrees((R_a.inv() * T_sm_true.rotation).magnitude())
            else:
                e_a, rot_a = math.nan, math.nan
            ray = T_sm_true.translation / np.linalg.norm(T_sm_true.translation)
            normal = T_sm_true.rotation.apply([0, 0, 1.0])
            c = d.corners_px
            side = float(np.mean(np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1)))
            margin = float(min(c[:, 0].min(), c[:, 1].min(), W - 1 - c[:, 0].max(), H - 1 - c[:, 1].max()))
            seen.append(
                Seen(d.marker_id, side, float(np.linalg.norm(T_sm_true.translation)),
                     float(np.degrees(np.arccos(min(abs(ray @ normal), 1.0)))), margin, mp.ambiguity,
                     bool(rot_p <= rot_a or math.isnan(rot_a)), e_p * 1e3, e_a * 1e3, rot_p, rot_a,
                     mp.reprojection_error_px)  # fmt: skip
            )
        records = []
        for md in mds:
            row = {"id": md.marker_id, "joint": md.ambiguity_ratio == 0, "ratio": md.ambiguity_ratio,
                   "sigma_mm": md.sigma_m * 1e3}  # fmt: skip
            for name, lis in (("att", with_att), ("plain", plain)):
                edge = lis.edge_from(md)
                if isinstance(edge, Rejection):
                    row[name] = edge.value
                    continue
                R_dw = Rotation.from_quat(edge.q_a_b_xyzw)
                row[name] = float(np.linalg.norm(-R_dw.inv().apply(edge.p_a_b) - truth.translation)) * 1e3
            records.append(row)
        now_ns = round(t * 1e9)
        listener.accept_many([(md, now_ns) for md in mds])
        result = graph.evaluate(now_ns)
        listener.set_estimates(result.poses)
        est = result.poses.get(ENTITY)
        if est is None or est.capture_time_us != t_us or est.covariance is None:
            continue
        e = truth.translation - np.asarray(est.p_world_m)
        C = np.asarray(est.covariance)[:3, :3]
        outputs.append(
            Output(j, t, float(np.linalg.norm(e)) * 1e3, float(np.sqrt(np.linalg.eigvalsh(C).max())) * 1e3,
                   float(e @ np.linalg.solve(C, e)), seen, records, view=j in in_view)  # fmt: skip
        )
    errs = np.array([o.err_mm for o in outputs])
    print(f"scenario {args.scenario}: {len(outputs)} outputs of {n} frames; RMSE {np.sqrt(np.mean(errs**2)):.2f} mm,"
          f" median {np.median(errs):.2f}, p95 {np.percentile(errs, 95):.2f}, max {errs.max():.1f}")  # fmt: skip
    for state, sel in (("view", True), ("blind", False)):
        v = np.array([o.err_mm for o in outputs if o.view is sel])
        if len(v):
            print(f"  {state}: {len(v)} outputs, RMSE {np.sqrt(np.mean(v**2)):.2f} mm, mean {v.mean():.2f}, max {v.max():.1f}")
    # The best per-frame alternative: the least error among every record (with or without attitude) and
    # every marker alone on either branch.
    best = []
    for o in outputs:
        alts = [r[k] for r in o.records for k in ("att", "plain") if isinstance(r[k], float)]
        alts += [s.err_primary_mm for s in o.markers] + [s.err_alt_mm for s in o.markers if not math.isnan(s.err_alt_mm)]
        best.append(min(alts) if alts else math.nan)
    best = np.array(best)
    print(f"best per-frame alternative (oracle): RMSE {np.sqrt(np.nanmean(best**2)):.2f} mm, max {np.nanmax(best):.1f}")
    for o, b in zip(outputs, best, strict=True):
        o.cls = classify(o, b, args.limit)
    tails = [o for o in outputs if o.err_mm > args.limit]
    total_sq = float(np.sum(errs**2))
    print(f"{len(tails)} outputs with error > {args.limit:g} mm; share of the squared error (RMSE^2) by class:")
    by = Counter(o.cls for o in tails)
    for cls in sorted(by):
        sq = sum(o.err_mm**2 for o in tails if o.cls == cls)
        print(f"  {cls}: {by[cls]:4d} outputs, {100 * sq / total_sq:5.1f} % of all squared error")
    rest = sum(o.err_mm**2 for o in outputs if o.err_mm <= args.limit)
    print(f"  (outputs <= {args.limit:g} mm: {len(outputs) - len(tails)}, {100 * rest / total_sq:.1f} %)")
    if args.live:
        live(args, {o.frame: o for o in outputs}, fps)
    print(f"the {args.worst} worst (t s, error mm, sigma mm, NEES3, class, best alternative mm | records | markers):")
    for o, b in sorted(zip(outputs, best, strict=True), key=lambda x: -x[0].err_mm)[: args.worst]:
        recs, marks = describe(o)
        print(f"  {o.t_s:6.3f}{' ' if o.view else 'B'} {o.err_mm:6.1f} {o.sigma_mm:6.1f} {o.nees3:6.1f} {o.cls} {b:6.1f} | {recs} | {marks}")
    return 0


def live(args: argparse.Namespace, offline: dict[int, Output], fps: float) -> None:
    """One live run (a real node, real MAVLink): each message against the offline output of the last frame
    at or before its capture time. A message > limit is ``e`` when that frame is more than 1.5 frame periods
    old (a prediction or a held pose in a gap), ``d`` when it is worse than the frame's output by more than
    half the limit (the live fusion or timing), else the frame's own offline class."""
    from atlas_onboard.sim.command import score_run
    from atlas_onboard.sim.runner import WARMUP_S, SimOptions, run

    overrides = {"fusion": {"filter": args.live}} if args.live != "graph" else {}
    sim = run(SimOptions(scenario=args.scenario, duration_s=args.duration, world_overrides=overrides))
    _, tracks = score_run(sim)
    track = tracks[ENTITY]
    inside = (track.arrival_s >= WARMUP_S) & (track.arrival_s <= args.duration)
    cap = track.capture_s[inside]
    p_true, _ = sim.world.truth_series(ENTITY, cap)
    err = np.linalg.norm(track.p_m[inside] - p_true, axis=1) * 1e3
    seen_live = live_observations(sim, fps)
    frames = sorted(offline)
    print(f"live run ({args.live}): {len(err)} messages, RMSE {np.sqrt(np.mean(err**2)):.2f} mm, median"
          f" {np.median(err):.2f}, p95 {np.percentile(err, 95):.2f}, max {err.max():.1f}")  # fmt: skip
    classes: Counter[str] = Counter()
    share: Counter[str] = Counter()
    rows = []
    for c, e in zip(cap, err, strict=True):
        k = np.searchsorted(frames, math.floor(c * fps + 1e-3), side="right") - 1
        o = offline[frames[k]] if k >= 0 else None
        age = c - o.t_s if o is not None else math.inf
        if e <= args.limit:
            cls = ""
        elif age > 1.5 / fps:
            cls = "e"
        elif e > o.err_mm + args.limit / 2:
            cls = "d"
        else:
            cls = o.cls or "c"
        classes[cls] += 1
        share[cls] += e**2
        if cls:
            rows.append((e, c, age, o, cls))
    total = float(np.sum(err**2))
    for cls in sorted(classes):
        print(f"  {cls or '<=limit'}: {classes[cls]:4d} messages, {100 * share[cls] / total:5.1f} % of all squared error")
    for e, c, age, o, cls in sorted(rows, key=lambda r: -r[0])[: args.worst]:
        off = f"frame {o.t_s:.3f} offline {o.err_mm:.1f} mm" if o is not None else "no frame"
        obs = seen_live.get(math.floor(c * fps + 1e-3), [])
        said = "; ".join(f"obs m{m} plain {v:.0f} s{sg:.1f} r{r:.2f}" for m, v, sg, r in obs) or "no live observation"
        print(f"  live {c:7.3f} {e:6.1f} mm {cls} age {age * 1e3:5.0f} ms | {said} | {off} | "
              f"{' | '.join(describe(o)) if o else ''}")


def live_observations(sim, fps: float) -> dict[int, list[tuple[int, float, float, float]]]:  # noqa: ANN001
    """Frame index -> the node's own observations broadcast in the run (marker, the drone position error
    of its chosen solution in mm, sigma mm, IPPE ratio), decoded from the hub's datagrams."""
    from atlas_onboard.mavlink import dialect

    parser = dialect.load().MAVLink(None)
    parser.robust_parsing = True
    world = sim.world.world
    out: dict[int, list[tuple[int, float, float, float]]] = {}
    for _arrival, data in sim.taps:
        for msg in parser.parse_buffer(data) or []:
            if msg.get_type() != "ATLAS_OBSERVATION" or msg.sensor_id not in world.sensors:
                continue
            sensor = world.sensors[msg.sensor_id]
            if sensor.entity != ENTITY or msg.marker_id not in world.markers:
                continue
            t = msg.time_usec / 1e6 - sim.epoch_s
            w, x, y, z = msg.q
            truth = sim.world.truth(t, (ENTITY,))[ENTITY]
            p = drone_from_sensor_marker(world.markers[msg.marker_id].T_entity_marker, sensor.T_entity_sensor,
                                         np.array([msg.x, msg.y, msg.z]), Rotation.from_quat([x, y, z, w]))  # fmt: skip
            err = float(np.linalg.norm(p - truth.translation)) * 1e3
            out.setdefault(math.floor(t * fps + 1e-3), []).append((msg.marker_id, err, msg.sigma * 1e3, msg.ambiguity))
    return out


def describe(o: Output) -> tuple[str, str]:
    """An output's records (J joint / S single, id, ratio, sigma, edge error with and without attitude) and
    markers (side, range, view angle, border margin, IPPE ratio, chosen branch near or far from the truth,
    rotation and drone error of both branches, refit residual)."""
    recs = "; ".join(
        f"{'J' if r['joint'] else 'S'}{r['id']} r{r['ratio']:.2f} s{r['sigma_mm']:.1f} "
        f"att {fmt(r['att'])} plain {fmt(r['plain'])}"
        for r in o.records
    )
    marks = "; ".join(
        f"m{s.marker_id} {s.side_px:.0f}px {s.range_m:.2f}m {s.view_deg:.0f}deg edge {s.margin_px:.0f}px "
        f"r{s.ratio:.2f} {'near' if s.chosen_near else 'FAR'} rot {s.rot_primary_deg:.1f}/{s.rot_alt_deg:.1f} "
        f"err {s.err_primary_mm:.0f}/{s.err_alt_mm:.0f} refit {s.refit_px:.2f}"
        for s in o.markers
    )
    return recs, marks


def fmt(v: object) -> str:
    return f"{v:.0f}" if isinstance(v, float) else str(v)


def classify(o: Output, best_mm: float, limit: float) -> str:
    if o.err_mm <= limit:
        return ""
    own = [r["att"] for r in o.records if isinstance(r["att"], float)]
    if own and min(own) <= limit and o.err_mm > min(own) + limit / 2:
        return "d"  # the frame's own edge was good: the fusion kept something worse
    singles = [s for s in o.markers]
    if len(o.records) == 1 and not o.records[0]["joint"] and singles:
        s = singles[0]
        kept = o.records[0]["att"]
        if isinstance(kept, float) and kept > limit and min(s.err_primary_mm, np.nan_to_num(s.err_alt_mm, nan=1e9)) <= limit:
            return "a"  # the other branch was good: the edge kept the wrong one
    if o.nees3 > 13.8 and any(s.margin_px < 10 or s.refit_px > 1.0 for s in singles):
        return "b"  # far outside its own covariance, at the border or with a poor fit
    if o.nees3 <= 13.8:
        return "c"  # within the 99.7 % ellipsoid of its own published covariance: an honest floor
    return "?"


if __name__ == "__main__":
    raise SystemExit(main())
