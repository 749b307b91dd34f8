"""Attacks on a node from its network, against the same node left alone.

A node runs paper-test1's drone with the simulator's camera path (by default the corners of its
tags from the geometry plus pixel noise, then the real PnP, sigma model and node; ``--rendered``:
rendered 1280x720 images and the real detector, which two loaded cores cannot run at 30 fps) and a
simulated autopilot; its one peer link is ``udpin`` on loopback, unsigned
or signed (``require: true``). A hostile process on the same network plays each attack while the
drone flies; the pose the autopilot received is scored against the truth over the same window as a
clean run (same scenario, seed and frames), per signing mode:

- ``random``: random datagrams with MAVLink 2 headers (right magic, random length, id, system id);
- ``malformed``: ATLAS_OBSERVATION with the right fingerprint and NaN/inf/1e38/0 fields, unknown
  sensor and marker ids and absurd stamps, from random system ids;
- ``spoof``: system 2 says, 30 times a second, that the drone's own camera sees a floor tag with
  the drone 1 m east of where it is, sigma 1 mm, fresh stamps;
- ``flood``: the same from 50 system ids, 120 Hz each (6,000 datagrams a second);
- ``replay``: the node's own signed (or unsigned) datagrams, captured on the link, sent back to it
  twice (a mesh echo, then a replay);
- ``wrong_key``: the spoof, signed with another key;
- the wire's (benchmarks/attack_wire.py): ``future_stamp`` (a signed frame stamped 2^48 - 1; signing
  on only), ``sources`` (one-byte datagrams from 500 addresses), ``partial`` (a partial frame before each
  real datagram), ``impostor`` (another autopilot behind the autopilot link), ``garbage`` (datagrams of
  bad frames). In every run a witness, the world's node (system 250), is a real peer on the link;
- the peers' (benchmarks/attack_peers.py, rows 1, 1b and 2, on an unsigned mesh: a forger holds no key of
  a signed one), against two nodes of the ``relay`` scene, one with its own view of the floor and one
  that sees only its leader: ``row1_own``, ``row1_own_reverse`` (a world camera forged with a sigma and a
  covariance that disagree), ``row1_relay``, ``row1b_relay`` (the leader's views forged), ``row2_relay``,
  ``row2_own`` (true views stamped 0.9 s ahead); their bars as attack_peers.py prints them.

Printed per run: what was sent, the node's counters that moved, the position error at the
autopilot (mean, median, p95, RMSE, max) and the latency from capture to the autopilot (median,
p95), beside the clean run's; then the bars:

- the RMSE during each attack within 10 % of the clean run's, its max error within 1 cm of the
  clean run's max, both over the camera frames whose pose reached the autopilot in both runs (the
  frames and their detections are the same in every run; on a loaded machine which frames get
  through is not, and one frame more or less with an ambiguous tag moves an RMSE by more than 10 %:
  the errors over all frames are printed too);
- 0 observations of the own entity's sensors accepted from the network;
- 0 observations, fused poses or TUNNEL decoded from unsigned or wrongly signed frames on a
  ``require: true`` link;
- at most one STATUSTEXT per reason per 10 s (the runs are shorter than 10 s: at most one each);
- pose messages per second at the autopilot during each attack at least 95 % of the clean run's;
- ``partial``: 0 of the witness's datagrams lost; ``sources``: the CPU time per send of the node's peer
  link within 2x of the clean run's, and 0 datagrams sent to the sources; ``future_stamp``: frames the
  witness (a right clock) accepts still arrive 10 s after it; ``impostor``: the autopilot found once,
  the configured one.

The node runs on core 1, this process (the attackers, the simulated autopilot) on core 0.

    python benchmarks/attack.py [--seconds S] [--attacks a,b,...] [--signing off,on]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import re
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import attack_peers
import numpy as np
from attack_wire import AFTER_ROW3_S, WireAttack, Witness, node_cpu_s, node_rss_mb, node_threads, wire_report

from atlas_onboard.config import load_world
from atlas_onboard.mavlink.signing import SIGNING_TICKS_PER_S, signing_timestamp
from atlas_onboard.service.install import write_key
from atlas_onboard.sim.command import autopilot_track
from atlas_onboard.sim.solo import Radio, SoloNode, forged_view, start_solo
from atlas_onboard.sim.world import SimWorld

SCENARIO = "paper-test1"
ENTITY = "ardrone"
OWN_SENSOR = 1
MARKER = 2
LIE_M = (1.0, 0.0, 0.0)
WIRE = ("future_stamp", "sources", "partial", "impostor", "garbage")
PEERS = attack_peers.ATTACKS  # rows 1, 1b and 2: what peers say, on an unsigned mesh
ATTACKS = ("random", "malformed", "spoof", "flood", "replay", "wrong_key", *WIRE, *PEERS)
START_S = 1.0  # the attack and the scoring start this long after the scenario
TAIL_S = 0.5  # and end this long before its end


class Attack:
    """One attack's sender: ``step(now_s)`` sends what is due; runs in its own thread."""

    def __init__(self, name: str, node: SoloNode, key: bytes | None, witness: Witness) -> None:
        self.witness = witness
        self.name = name
        self.node = node
        self.key = key
        self.radio = Radio(node.peer_port)
        self.world = load_world(node.world_file)
        self.sim_world = SimWorld(node.scenario)
        self.fp = self.world.fingerprint()
        self.rng = random.Random(1)
        self.captured: list[bytes] = []
        self.what = ""

    def plan(self) -> tuple[float, Callable[[float], None]]:
        return self._plan()

    def _lie(self, now_s: float):  # the drone 1 m off, as seen by its own camera
        return forged_view(
            self.world, self.sim_world, ENTITY, OWN_SENSOR, MARKER, now_s - self.node.epoch_s, LIE_M, 0.001,
            int(now_s * 1e6),
        )  # fmt: skip

    def _plan(self) -> tuple[float, Callable[[float], None]]:
        r, radio, seq = self.rng, self.radio, [0]
        if self.name == "random":
            self.what = "random datagrams with MAVLink 2 headers, 1,300/s"

            def step(_now: float) -> None:
                n = r.randrange(0, 120)
                head = bytes([0xFD, n, r.choice((0, 0, 1)), 0, r.randrange(256), r.randrange(256), r.randrange(256)])
                ident = r.choice((r.randrange(1 << 24), 42000, 42001, 0, 385)).to_bytes(3, "little")
                radio.send(head + ident + os.urandom(n + 2 + r.choice((0, 13))))

            return 1300.0, step
        if self.name == "malformed":
            self.what = (
                "ATLAS_OBSERVATION, right fingerprint, NaN/inf/1e38/0 fields, unknown ids, absurd stamps, 1,200/s"
            )
            bad = (math.nan, math.inf, -math.inf, 1e38, 0.0)

            def step(now: float) -> None:
                md = self._lie(now)
                seq[0] += 1
                fields = {
                    r.choice(("x", "y", "z", "sigma", "reprojection_error", "ambiguity")): r.choice(bad),
                    "sensor_id": r.choice((OWN_SENSOR, 999, 65535, 0)),
                    "marker_id": r.choice((MARKER, 4000, 65535)),
                    "time_usec": r.choice((int(now * 1e6), 0, 2**63, int(now * 1e6) + 3_600_000_000)),
                    "q": r.choice(([0.0] * 4, [math.nan] * 4, list(md.q_sensor_marker_wxyz))),
                }
                radio.send(radio.observation(md, self.fp, r.randrange(1, 256), seq=seq[0] & 0xFFFF, **fields))

            return 1200.0, step
        if self.name in ("spoof", "wrong_key"):
            key = os.urandom(32) if self.name == "wrong_key" else None
            self.what = "system 2: the own camera sees the drone 1 m off, sigma 1 mm, 30 Hz" + (
                ", signed with another key" if key else ""
            )

            def step(now: float) -> None:
                seq[0] += 1
                radio.send(radio.observation(self._lie(now), self.fp, 2, key, seq=seq[0] & 0xFFFF))

            return 30.0, step
        if self.name == "flood":
            self.what = "50 system ids x 120 Hz: the own camera sees the drone 1 m off (6,000/s)"

            frames: list[bytes] = []

            def step(now: float) -> None:
                # The 50 frames are packed anew every 10th tick (83 ms, stamps still fresh): this process
                # shares the machine with the node, an attacker on the radio would not.
                seq[0] += 1
                if seq[0] % 10 == 1:
                    md = self._lie(now)
                    frames[:] = [radio.observation(md, self.fp, sysid, seq=seq[0] & 0xFFFF) for sysid in range(2, 52)]
                for frame in frames:
                    radio.send(frame)

            return 120.0, step
        if self.name == "replay":
            self.what = "the node's datagrams to the witness, eavesdropped, sent back twice (echo, then replay)"
            pending: list[tuple[float, bytes]] = []
            taken = [len(self.witness.captured)]

            def step(now: float) -> None:
                new = self.witness.captured[taken[0] :]
                taken[0] += len(new)
                for data in new:
                    pending.extend(((now, data), (now + 0.5, data)))  # at once, and 0.5 s later
                while pending and pending[0][0] <= now:
                    radio.send(pending.pop(0)[1])
                pending.sort(key=lambda item: item[0])

            return 100.0, step
        raise ValueError(self.name)


def drive(plan: tuple[float, Callable[[float], None]], t0_s: float, t1_s: float, stop: threading.Event) -> None:
    """Call the attack's step at its rate from ``t0_s`` to ``t1_s`` (wall clock)."""
    rate_hz, step = plan
    period_s, next_s = 1.0 / rate_hz, t0_s
    while not stop.is_set() and time.time() < t1_s:
        step(time.time())
        next_s += period_s
        time.sleep(max(0.0, next_s - time.time()))


def _pin(node: SoloNode) -> None:
    """The node on core 1, this process on core 0 (where the machine has two)."""
    if len(os.sched_getaffinity(0)) >= 2:
        os.sched_setaffinity(node.proc.pid, {1})
        os.sched_setaffinity(0, {0})


def one_run(attack: str | None, seconds: float, key_path: Path | None, rendered: bool, seed: int = 0) -> dict:
    signing = {"key_file": str(key_path), "require": True} if key_path is not None else None
    node = start_solo(SCENARIO, seconds, signing=signing, geometric=not rendered, seed=seed, world_node=True)
    _pin(node)
    key = key_path.read_bytes() if key_path is not None else None
    witness = Witness(node, key)
    sender: Attack | WireAttack | None = None
    if attack in WIRE:
        sender = WireAttack(attack, node, key, witness)
    elif attack is not None:
        sender = Attack(attack, node, key, witness)
    stop = threading.Event()
    thread = None
    extra: dict = {}
    try:
        epoch = node.start_scenario()  # the node's links are open: the witness's first HEARTBEAT is heard
        witness.start()
        if sender is not None:
            thread = threading.Thread(
                target=drive, args=(sender.plan(), epoch + START_S, epoch + seconds - TAIL_S, stop), daemon=True
            )
            time.sleep(max(0.0, epoch + START_S - time.time()))
            thread.start()
        time.sleep(max(0.0, epoch + seconds + 0.3 - time.time()))
        extra["cpu_s"] = node_cpu_s(node.proc.pid)
        extra["rss_mb"] = node_rss_mb(node.proc.pid)
        extra["threads"] = node_threads(node.proc.pid)
        states = sorted((node.run_dir / "state").glob("signing-*.json"))  # saved every 10 s; gone after stop
        if states:
            saved = int(json.loads(states[0].read_text(encoding="utf-8"))["timestamp"])
            extra["state_ahead_s"] = (saved - signing_timestamp(time.time())) / SIGNING_TICKS_PER_S
    finally:
        stop.set()
        if thread is not None:
            thread.join(5.0)
        witness.stop()
        if isinstance(sender, WireAttack):
            extra["to_sources"] = sender.to_sources()
            extra["first_s"] = sender.first_s
            sender.close()
        elif sender is not None:
            sender.radio.close()
        code = node.stop()
    if code != 0:
        sys.exit(f"node exited with {code}: {node.log[-2000:]}")
    first_s = extra.get("first_s")
    if first_s is not None:
        extra["after_row3"] = witness.accepted_since(first_s + AFTER_ROW3_S)
    extra["autopilots_found"] = re.findall(r"autopilot found: system (\d+)", node.log)
    extra["witness"] = (witness.heartbeats, len(witness.received), sum(ok for _, _, ok in witness.received))
    track = autopilot_track(node.autopilot.snapshot(), node.epoch_s)
    t0, t1 = START_S, seconds - TAIL_S
    inside = (track.arrival_s >= t0) & (track.arrival_s <= t1)
    p_true, _ = SimWorld(node.scenario).truth_series(ENTITY, track.capture_s[inside])
    err_m = np.linalg.norm(track.p_m[inside] - p_true, axis=1)
    lat_ms = (track.arrival_s[inside] - track.capture_s[inside]) * 1e3
    texts = Counter(re.sub(rb" \(\+\d+\)$", b"", t) for t in node.autopilot.statustexts)
    return {
        "attack": attack or "clean",
        "what": sender.what if sender is not None else "",
        "sent": sender.radio.sent if sender is not None else 0,
        "counters": node.final_counters(),
        "err_m": err_m,
        "capture_s": track.capture_s[inside],
        "lat_ms": lat_ms,
        "statustext_max": max(texts.values(), default=0),
        "statustexts": len(node.autopilot.statustexts),
        "rate_hz": int(inside.sum()) / (t1 - t0),
        "origin_sets": node.autopilot.other.get("SET_GPS_GLOBAL_ORIGIN", 0),
        "timesync_to_others": sum((s, c) != (node.system_id, 1) for _, _, s, c in node.autopilot.timesync_replies),
        **extra,
    }


INTERESTING = re.compile(
    r"^(rejected_|refused_from_|peer_observations|accepted$|inbox_dropped|statustext_suppressed|"
    r"heartbeat_not_from|origin_not_from|attitude_|timesync_not|"
    r"peer0_(rx_atlas|rx_tunnel|rx_heartbeat|rejected_|signature_|signing_|kernel_drops|tx_statustext|"
    r"udp_|datagrams_cut))"
)


def summary(run: dict) -> str:
    e, lat = run["err_m"] * 100, run["lat_ms"]
    if len(e) == 0:
        return "no pose reached the autopilot"
    return (
        f"n {len(e):4d}  error cm: mean {e.mean():5.2f} median {np.median(e):5.2f} p95 {np.percentile(e, 95):5.2f}"
        f" RMSE {math.sqrt(float(np.mean(e**2))):5.2f} max {e.max():5.2f}"
        f"  latency ms: median {np.median(lat):5.1f} p95 {np.percentile(lat, 95):5.1f}"
    )


def matched(run: dict, clean: dict) -> tuple[np.ndarray, np.ndarray]:
    """The errors of the two runs at the camera frames (capture times) whose pose reached the
    autopilot in both: the rendered frames and their detections are the same in every run, so what
    differs there is what the attack did, not which frames a loaded machine got through."""
    a = {round(float(t), 4): e for t, e in zip(run["capture_s"], run["err_m"], strict=True)}
    b = {round(float(t), 4): e for t, e in zip(clean["capture_s"], clean["err_m"], strict=True)}
    common = sorted(a.keys() & b.keys())
    return np.array([a[t] for t in common]), np.array([b[t] for t in common])


def rms(e: np.ndarray) -> float:
    return math.sqrt(float(np.mean(e**2))) if len(e) else math.nan


def worst(e: np.ndarray) -> float:
    return float(e.max()) if len(e) else math.nan


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="length of each run (default 6)")
    ap.add_argument("--attacks", default=",".join(ATTACKS), help=f"comma-separated, of {', '.join(ATTACKS)}")
    ap.add_argument("--signing", default="off,on", help="off, on or both (default off,on)")
    ap.add_argument(
        "--rendered",
        action="store_true",
        help="rendered images and the real detector (default: the simulator's corners from the geometry plus"
        " noise, then the same PnP, sigma model and node; two loaded cores do not keep 30 fps of 1280x720)",
    )
    args = ap.parse_args()
    chosen = [a for a in args.attacks.split(",") if a]
    attacks = [a for a in chosen if a not in PEERS]
    unknown = set(chosen) - set(ATTACKS)
    if unknown:
        ap.error(f"unknown attacks: {', '.join(sorted(unknown))}")
    bars: list[tuple[str, float, str, float, bool]] = []
    own_accepted = 0
    unsigned_decoded = 0
    statustext_max = 0
    with tempfile.TemporaryDirectory(prefix="atlas-attack-") as tmp:
        key_path = Path(tmp) / "swarm.key"
        write_key(key_path)
        for mode in args.signing.split(","):
            key = key_path if mode == "on" else None
            clean = one_run(None, args.seconds, key, args.rendered)
            statustext_max = max(statustext_max, clean["statustext_max"])
            print(f"\n=== signing {mode}: clean run, {SCENARIO} for {args.seconds:g} s, scored {START_S:g}"
                  f" to {args.seconds - TAIL_S:g} s")  # fmt: skip
            print(f"  clean      {summary(clean)}")
            peers = [a for a in chosen if a in PEERS]
            if peers and mode == "off":  # lies in frames a forger can make: on a signed mesh it holds no key
                attack_peers.play(peers, max(args.seconds, attack_peers.SECONDS), bars)
            elif peers:
                print("\n  rows 1, 1b, 2: skipped (a forger holds no key: spoof and wrong_key show its frames refused)")
            for attack in attacks:
                if attack == "future_stamp" and mode == "off":
                    print("\n  future_stamp: skipped (an unsigned link checks no timestamp)")
                    continue
                seconds = max(args.seconds, START_S + AFTER_ROW3_S + 2.0) if attack == "future_stamp" else args.seconds
                run = one_run(attack, seconds, key, args.rendered)
                c = {k: v for k, v in run["counters"].items() if INTERESTING.match(k) and v}
                by_origin = {k: v for k, v in c.items() if k.startswith("refused_from_")}
                rest = {k: v for k, v in c.items() if not k.startswith("refused_from_")}
                print(f"\n  {attack}: {run['what']}; sent {run['sent']:,} datagrams")
                print(f"    counters: {' '.join(f'{k}={v}' for k, v in sorted(rest.items()))}")
                if by_origin:
                    top = sorted(by_origin.items(), key=lambda kv: -kv[1])[:3]
                    most = ", ".join(f"{k[13:]}: {v}" for k, v in top)
                    print(f"    refused from {len(by_origin)} origins, most: {most}")
                print(
                    f"    STATUSTEXT at the autopilot: {run['statustexts']}, most of one reason {run['statustext_max']}"
                )
                print(f"    attack     {summary(run)}")
                print(f"    clean      {summary(clean)}")
                e_attack, e_clean = matched(run, clean)
                print(
                    f"    the {len(e_attack)} frames both runs sent, error cm: attack RMSE {rms(e_attack) * 100:5.2f}"
                    f" max {worst(e_attack) * 100:5.2f}; clean RMSE {rms(e_clean) * 100:5.2f}"
                    f" max {worst(e_clean) * 100:5.2f}"
                )
                ratio = rms(e_attack) / rms(e_clean) if len(e_attack) >= 10 else math.inf
                excess_cm = (worst(e_attack) - worst(e_clean)) * 100 if len(e_attack) >= 10 else math.inf
                bars.append((f"rmse_ratio_{attack}_signing_{mode}", ratio, "x", 1.10, ratio <= 1.10))
                bars.append((f"max_excess_{attack}_signing_{mode}", excess_cm, "cm", 1.0, excess_cm <= 1.0))
                wire_report(attack, mode, run, clean, bars)
                # paper-test1 has no other node: every observation accepted from the network is an attack's
                own_accepted += run["counters"].get("peer_observations", 0)
                if mode == "on" and attack != "replay":  # every protected frame of these is unsigned or mis-signed
                    cc = run["counters"]
                    unsigned_decoded += sum(cc.get(f"peer0_rx_{k}", 0) for k in ("atlas_observation", "tunnel",
                                                                                  "atlas_fused_pose"))  # fmt: skip
                if seconds <= 10.0:  # at most one per 10 s: over a longer run, two may be right
                    statustext_max = max(statustext_max, run["statustext_max"])
    print()
    for name, value, unit, limit, ok in bars:
        print(f"BAR {name} {value:.3f} {unit} {limit:g} {'pass' if ok else 'fail'}")
    print(f"BAR own_sensor_observations_accepted {own_accepted} count 0 {'pass' if own_accepted == 0 else 'fail'}")
    if "on" in args.signing.split(","):
        ok = unsigned_decoded == 0
        print(f"BAR unsigned_frames_decoded_on_require_link {unsigned_decoded} count 0 {'pass' if ok else 'fail'}")
    ok = statustext_max <= 1
    print(f"BAR statustext_per_reason_per_10s {statustext_max} count 1 {'pass' if ok else 'fail'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
