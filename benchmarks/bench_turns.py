"""Tracking through turns: the detector predicting where the markers move from the autopilot's attitude
(issue 19: ``R_prev_now`` from :class:`atlas_onboard.core.attitude.CameraTurn`) against its anchor, the
same detector predicting from the markers' last image motion (no attitude), on the same frames.

The frames are the simulator's images of the drone's camera, rendered here: ``hard-near`` and ``hard``
(figure-eight flights with yaw swings of up to 50 deg/s, 640x480 with distortion, blur and noise, textured
floor), and ``turns``: hard-near's flight with its yaw swings four times as fast (up to 195 deg/s). Three
detectors see every frame in order, interleaved frame by frame: the anchor (image motion, no attitude),
and two given the turn from an attitude as the node reads it: the truth 15 ms earlier (the link's delay,
which the node's boot-clock mapping does not remove) with a per-run bias on roll and pitch and per-sample
noise, 0.5 degree (``attitude``: the simulated autopilot's, pessimistic from frame to frame) or 0.05
degree (``gyro-grade``: an EKF's attitude, integrated from the gyros, between two frames).

Per detector: recall (markers fully in view, as the simulator's truth says, that the detector found),
over all frames and over the frames of fast turns (the camera turned by more than ``FAST_DEG`` since
the previous frame); the share of frames spent hunting (nothing tracked); the detector's thread CPU time
per frame, mean, median and p95, for tracking and hunting frames. Bars, with the simulated autopilot's
attitude: recall >= the anchor's (all frames and fast turns), mean time per frame <= 1.05x the anchor's.

    taskset -c 0 python benchmarks/bench_turns.py [--duration 30] [--scenario hard-near|turns|hard|all]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_hard import ENTITY
from scipy.spatial.transform import Rotation

from atlas_onboard.core.attitude import CameraTurn
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.sim import scenarios
from atlas_onboard.sim import trajectories as tj
from atlas_onboard.sim.autopilot import SimAutopilot
from atlas_onboard.sim.camera import FrameRenderer, camera_seed
from atlas_onboard.sim.scenario import Scenario
from atlas_onboard.sim.world import SimWorld

FAST_DEG = 3.0  # per frame: 90 deg/s at 30 fps
TURNS_AMPLITUDE_DEG, TURNS_PERIOD_S = 70.0, 2.25  # up to 195 deg/s, a quick look around
GYRO_NOISE_DEG = 0.05  # an EKF's attitude from frame to frame: gyro-integrated, far smoother than its tilt error


def noisy_attitude(sim: SimWorld, seed: int, noise_deg: float | None = None):
    """The simulated autopilot's attitude as the node reads it at a capture time ``t`` (s); its per-sample
    noise ``noise_deg`` (None: the simulated autopilot's)."""
    ap = SimAutopilot.__dataclass_fields__
    delay_s = ap["attitude_delay_s"].default
    noise_rad = math.radians(ap["attitude_noise_deg"].default if noise_deg is None else noise_deg)
    rng = np.random.default_rng(seed + 7)
    bias = rng.normal(0.0, math.radians(ap["attitude_bias_deg"].default), 2)

    def at(t: float) -> Rotation:
        R = sim.truth(max(t - delay_s, 0.0), (ENTITY,))[ENTITY].rotation
        return Rotation.from_rotvec(np.r_[bias + rng.normal(0.0, noise_rad, 2), 0.0]) * R

    return at


def stats(ms: list[float]) -> str:
    if not ms:
        return "        -        -        -     0"
    a = np.array(ms)
    return f"{a.mean():9.2f} {np.median(a):8.2f} {np.percentile(a, 95):8.2f} {len(a):5d}"


def scene(name: str) -> Scenario:
    """``hard-near`` as flown, or (``turns``) the same flight with its yaw swings four times as fast."""
    if name != "turns":
        return scenarios.get(name)
    base = scenarios.get("hard-near")
    drone = base.trajectories[ENTITY]
    fast = replace(drone, yaw=tj.slow_yaw(0.0, TURNS_AMPLITUDE_DEG, TURNS_PERIOD_S))
    return replace(base, name="turns", trajectories={ENTITY: fast})


def run(scenario_name: str, duration_s: float, seed: int = 0) -> dict[str, dict]:
    scenario = scene(scenario_name)
    world = scenario.world()
    sim = SimWorld(scenario)
    out: dict[str, dict] = {}
    for sensor, intr in sim.cameras.values():
        if sensor.entity != ENTITY:
            continue
        render = FrameRenderer(scenario, world, sensor, camera_seed(seed, sensor.id))
        fps, n = render.fps, math.floor(duration_s * render.fps)
        cal = intr.calibration()
        variants = {  # name: (detector, attitude at t or None, its turn since the previous frame)
            "image motion": (Detector(sensor, world, cal, decimate=2.0), None, None),
            "attitude": (Detector(sensor, world, cal, decimate=2.0), noisy_attitude(sim, seed),
                         CameraTurn(sensor.T_entity_sensor.rotation)),
            "gyro-grade": (Detector(sensor, world, cal, decimate=2.0), noisy_attitude(sim, seed, GYRO_NOISE_DEG),
                           CameraTurn(sensor.T_entity_sensor.rotation)),
        }  # fmt: skip
        res = {k: {"seen": 0, "found": 0, "fast_seen": 0, "fast_found": 0, "track": [], "hunt": []} for k in variants}
        previous_R = None
        for j in range(n):
            t = j / fps
            truth = sim.truth(t)
            want = {s.marker.id for s in sim.sightings(sensor.id, truth, t)}
            R_true = (truth[ENTITY] * sensor.T_entity_sensor).rotation
            fast = previous_R is not None and math.degrees((previous_R.inv() * R_true).magnitude()) > FAST_DEG
            previous_R = R_true
            img = render(j)
            for name, (det, attitude, turn) in variants.items():
                R = turn.since_last(attitude(t)) if turn is not None else None
                state = "track" if det.tracking else "hunt"
                t0 = time.thread_time_ns()
                det.detect(img, round(t * 1e6), R)
                res[name][state].append((time.thread_time_ns() - t0) / 1e6)
                got = len(want & set(det.report.found))
                res[name]["seen"] += len(want)
                res[name]["found"] += got
                if fast:
                    res[name]["fast_seen"] += len(want)
                    res[name]["fast_found"] += got
        out[f"{scenario_name}:{sensor.name}"] = res
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of each flight (default 30)")
    ap.add_argument(
        "--scenario",
        choices=("hard-near", "turns", "hard", "all"),
        default="all",
        help="hard-near, turns (hard-near with fast yaw swings), hard, or all (default)",
    )
    args = ap.parse_args(argv)
    names = ("hard-near", "turns", "hard") if args.scenario == "all" else (args.scenario,)
    bars: list[tuple[str, float, str, str, bool]] = []
    for name in names:
        for cam, res in run(name, args.duration).items():
            print(f"\n{cam}: {args.duration:g} s; recall = markers fully in view that were found")
            print(f"{'prediction':13s} {'recall':>7s} {'fast turns':>11s} {'hunting':>8s}   "
                  f"{'state':5s} {'mean ms':>9s} {'median':>8s} {'p95':>8s} {'n':>5s}")  # fmt: skip
            for k, r in res.items():
                frames = len(r["track"]) + len(r["hunt"])
                recall = r["found"] / max(r["seen"], 1)
                fast = r["fast_found"] / max(r["fast_seen"], 1)
                hunting = len(r["hunt"]) / max(frames, 1)
                for i, state in enumerate(("track", "hunt")):
                    head = f"{k:13s} {recall:7.4f} {fast:11.4f} {hunting:8.3f}" if i == 0 else " " * 42
                    print(f"{head}   {state:5s} {stats(r[state])}")
                r["recall"], r["fast"] = recall, fast
                r["mean"] = statistics.fmean(r["track"] + r["hunt"]) if frames else math.nan
            plain, att = res["image motion"], res["attitude"]
            print(f"fast turns: {plain['fast_seen']} marker sightings; time ratio attitude / image motion "
                  f"{att['mean'] / plain['mean']:.3f}")  # fmt: skip
            bars.append((f"{cam}.recall_gain", 100 * (att["recall"] - plain["recall"]), "pts", "0",
                         att["recall"] >= plain["recall"]))  # fmt: skip
            if plain["fast_seen"]:  # a scene without fast turns has no such bar
                bars.append((f"{cam}.fast_turn_recall_gain", 100 * (att["fast"] - plain["fast"]), "pts", "0",
                             att["fast"] >= plain["fast"]))  # fmt: skip
            ratio = att["mean"] / plain["mean"]
            bars.append((f"{cam}.time_ratio", ratio, "ratio", "1.05", ratio <= 1.05))
    print()
    for name, value, unit, limit, ok in bars:
        print(f"BAR {name} {value:.4g} {unit} {limit} {'pass' if ok else 'fail'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
