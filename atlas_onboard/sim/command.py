"""``atlas-onboard sim``: run a scenario, score it against ground truth, print and write the results."""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import frames
from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import report, scenarios
from atlas_onboard.sim.autopilot import Received
from atlas_onboard.sim.runner import WARMUP_S, SimOptions, SimRun, run
from atlas_onboard.sim.world import FRESH_S


def autopilot_track(records: list[Received], epoch_s: float) -> report.Track:
    """What the flight controller received, back in ENU/FLU, with times relative to the epoch."""
    n = len(records)
    q_ned = np.zeros((n, 4))
    if n:
        # VISION_POSITION_ESTIMATE carries roll/pitch/yaw, ODOMETRY a quaternion (w first).
        has_q = np.array([r.q_wxyz is not None for r in records])
        wxyz = np.array([r.q_wxyz if r.q_wxyz is not None else (1.0, 0.0, 0.0, 0.0) for r in records], dtype=float)
        rpy = np.array([r.rpy_rad if r.rpy_rad is not None else (0.0, 0.0, 0.0) for r in records], dtype=float)
        q_ned = np.where(has_q[:, None], wxyz[:, [1, 2, 3, 0]], Rotation.from_euler("ZYX", rpy[:, ::-1]).as_quat())
    xyz = np.array([r.xyz_m for r in records], dtype=float).reshape(n, 3)
    if n:
        T = frames.ned_frd_to_enu_flu(RigidTransform.from_components(xyz, Rotation.from_quat(q_ned)))
        p, q = T.translation.reshape(n, 3), T.rotation.as_quat().reshape(n, 4)
        q_ned = Rotation.from_quat(q_ned).as_quat().reshape(n, 4)  # normalized, as before
    else:
        p, q = np.zeros((0, 3)), np.zeros((0, 4))
    return report.Track(
        capture_s=np.array([r.usec / 1e6 - epoch_s for r in records]),
        arrival_s=np.array([r.arrival_s - epoch_s for r in records]),
        p_m=p,
        q_xyzw=q,
        p_ned_m=xyz,
        q_ned_frd_xyzw=q_ned,
        covariance_ned_frd=report.covariance_from_upper_triangle(
            np.array([r.covariance for r in records], dtype=float).reshape(n, 21)
        ),
        reset_counter=np.array([r.reset_counter for r in records], dtype=np.int64),
    )


def decode_taps(sim: SimRun) -> tuple[dict[str, report.Track], Counter[str]]:
    """Fused poses broadcast by the nodes (per entity) and observation counts (per entity), from the
    datagrams that crossed the hub."""
    from atlas_onboard.mavlink import dialect

    d = dialect.load()
    names = sim.world.world.entity_names
    markers, sensors = sim.world.world.markers, sim.world.world.sensors
    rows: dict[str, list[tuple[float, float, list[float], list[float], int]]] = {}
    observations: Counter[str] = Counter()
    parser = d.MAVLink(None)
    parser.robust_parsing = True
    for arrival, data in sim.taps:
        for msg in parser.parse_buffer(data) or []:
            kind = msg.get_type()
            if kind == "ATLAS_FUSED_POSE" and msg.frame_index == 0 and msg.entity_index < len(names):
                w, x, y, z = msg.q
                rows.setdefault(names[msg.entity_index], []).append(
                    (msg.time_usec / 1e6 - sim.epoch_s, arrival - sim.epoch_s, [msg.x, msg.y, msg.z], [x, y, z, w],
                     msg.n_observations)
                )  # fmt: skip
            elif kind == "ATLAS_OBSERVATION" and WARMUP_S <= arrival - sim.epoch_s <= sim.duration_s:
                m, s = markers.get(msg.marker_id), sensors.get(msg.sensor_id)
                for name in {m.entity if m else None, s.entity if s else None} - {None}:
                    observations[name] += 1  # type: ignore[index]
    tracks = {}
    for name, r in rows.items():
        r.sort(key=lambda row: row[0])
        tracks[name] = report.Track(
            capture_s=np.array([row[0] for row in r]), arrival_s=np.array([row[1] for row in r]),
            p_m=np.array([row[2] for row in r]), q_xyzw=np.array([row[3] for row in r]),
            n_observations=np.array([row[4] for row in r], dtype=float),
        )  # fmt: skip
    return tracks, observations


def score_run(sim: SimRun) -> tuple[report.RunReport, dict[str, report.Track]]:
    """Per-entity figures of a finished run (drones: what their autopilot got; others: fused poses)."""
    fused, observations = decode_taps(sim)
    sc = sim.scenario
    t0, t1 = WARMUP_S, sim.duration_s
    rates = {}
    for s in sim.world.cameras.values():
        sensor, intr = s
        cam = sensor.camera
        rates[f"{sensor.entity}.{sensor.name}"] = f"{intr.width_px}x{intr.height_px} @ {cam.fps:g} Hz"
    if sc.mocap is not None:
        rates[f"world.{sc.mocap.sensor}"] = f"motion capture @ {sc.mocap.rate_hz:g} Hz"
    rep = report.RunReport(sc.name, sim.duration_s, 0, "real time (wall clock); every node a separate process", rates)
    tracks: dict[str, report.Track] = {}
    # A drone's autopilot needs a pose at most 200 ms old; fused poses go out at 5 Hz (0.5 s).
    fresh = {"autopilot": FRESH_S, "fused": 0.5, "none": FRESH_S}
    expected = {f: sim.world.expected_availability(t0, t1, f) for f in set(fresh.values())}
    for name in sc.scored:
        if name in sim.autopilots:
            track = autopilot_track(sim.autopilots[name].snapshot(), sim.epoch_s)
            source = "autopilot"
            if name in fused:  # the number of measurements, for the plots
                track.n_observations = np.interp(track.capture_s, fused[name].capture_s, fused[name].n_observations)
        elif name in fused:
            track, source = fused[name], "fused"
        else:
            track, source = report.Track(*(np.zeros((0, k)) for k in (0, 0, 3, 4))), "none"  # type: ignore[arg-type]
            track.capture_s = track.arrival_s = np.zeros(0)
        tracks[name] = track
        f = fresh[source]
        score = report.score(name, source, track, sim.world, t0, t1, expected[f].get(name, 0.0), f)
        score.detections_per_s = observations[name] / (t1 - t0)
        rep.entities.append(score)
    rep.landing = sim.landing
    scores = [*rep.entities, *([sim.landing] if sim.landing is not None else [])]
    for key, limit in sc.bars.items():
        name, metric = key.split(".")
        got = next((getattr(e, metric) for e in scores if e.entity == name and hasattr(e, metric)), float("nan"))
        got = float("inf") if got is None else got  # a landing that did not touch down
        ok = bool(got >= limit) if metric == "availability" else bool(got <= limit)
        rep.bars.append({"name": f"{sc.name}.{key}", "value": got, "limit": limit, "pass": ok})
    return rep, tracks


@contextlib.contextmanager
def _terminate_cleanly() -> Iterator[None]:
    """SIGTERM (a service manager, a CI timeout, ``kill``) ends the run as an exception would: its nodes
    stopped and its temporary folders (run, rendered frames) removed, where the default action would
    leave them behind. Exit status 143, as the signal's."""

    def stop(signum: int, _frame: object) -> None:
        sys.stderr.write("atlas-onboard sim: terminated\n")
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _cmd_sim(args: argparse.Namespace) -> int:
    overrides: dict[str, dict[str, object]] = {}
    for item in args.set or []:
        key, sep, value = item.partition("=")
        section, dot, name = key.partition(".")
        if not sep or not dot or section != "fusion":
            raise AtlasError(f"--set: expected fusion.KEY=VALUE, got {item!r}")
        overrides.setdefault(section, {})[name] = yaml.safe_load(value)
    options = SimOptions(
        scenario=args.scenario, duration_s=args.duration, seed=args.seed, out_dir=args.out, world_overrides=overrides
    )
    with _terminate_cleanly():
        sim = run(options, progress=lambda msg: print(f"atlas-onboard sim: {msg}", file=sys.stderr))
    rep, tracks = score_run(sim)
    rep.seed = args.seed
    if args.json:
        print(rep.to_json())
    else:
        print(f"scenario {rep.scenario}: {scenarios.get(rep.scenario).description}")
        print(f"{rep.duration_s:g} s, {rep.clock}; scored from {WARMUP_S:g} s")
        print("cameras: " + "; ".join(f"{k} {v}" for k, v in rep.rates.items()))
        print(rep.table())
        for bar in rep.bars:
            print(f"bar {bar['name']}: {bar['value']:.4g} (limit {bar['limit']:g}) {'pass' if bar['pass'] else 'FAIL'}")
    if args.out is not None:
        write_outputs(Path(args.out), rep, tracks, sim)
    return 0


def write_outputs(out: Path, rep: report.RunReport, tracks: dict[str, report.Track], sim: SimRun) -> None:
    """report.json, TUM trajectories (estimate and ground truth) and Figure 6/7 plots per entity."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise AtlasError(f"--out: cannot create {out}: {exc.strerror}") from None
    (out / "report.json").write_text(rep.to_json(), encoding="utf-8")
    for name, track in tracks.items():
        report.write_tum(out / f"{name}-estimate.tum", track.capture_s, track.p_m, track.q_xyzw)
        t = np.arange(0.0, sim.duration_s, 0.01)
        p, q = sim.world.truth_series(name, t)
        report.write_tum(out / f"{name}-groundtruth.tum", t, p, q)
        report.plot_entity(out / f"{name}.png", name, track, sim.world, WARMUP_S, sim.duration_s)


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``sim``."""
    p = sub.add_parser(
        "sim",
        help="run a SITL-style simulation: real nodes, rendered cameras, simulated autopilots, loopback MAVLink",
        description="Run a built-in scenario with one real node process per drone and report the accuracy"
        " against ground truth. Scenarios: "
        + ", ".join(f"{s.name} ({s.description})" for s in scenarios.SCENARIOS.values()),
    )
    p.add_argument("--scenario", default=scenarios.DEFAULT, choices=sorted(scenarios.SCENARIOS))
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's own)")
    p.add_argument("--out", type=Path, default=None, help="write report.json, TUM trajectories and PNG plots here")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--seed", type=int, default=0, help="seed of the pixel noise")
    p.add_argument(
        "--set", action="append", metavar="fusion.KEY=VALUE",
        help="override a fusion setting of the scenario's world file, e.g. --set fusion.path=dijkstra",
    )  # fmt: skip
    p.set_defaults(func=_cmd_sim)
