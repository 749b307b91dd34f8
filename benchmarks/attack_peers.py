"""Peers that lie about what they see, on an unsigned mesh, against a node with a real camera path and
the same node left alone: rows 1, 1b and 2 of ``benchmarks/attack.py``, which plays them with the
others (this script alone plays only these, with attack.py's scoring).

Two nodes of the ``relay`` scenario (:mod:`atlas_onboard.sim.peerplay`), each with the simulator's
camera path (corners from the geometry plus pixel noise, then the real PnP and node) and a simulated
autopilot: ``own``, drone_a, which sees the floor tags itself; ``relay``, drone_b, which sees only
drone_a's back marker and gets drone_a's views of the floor (played here, the truth, 15 a second).
The attacks, each from ``START_S`` to ``TAIL_S`` before the end:

- ``row1_own``: the world camera's view of drone_a's marker (forging the world node's system id),
  drone_a 20 m east, sigma 0.1 mm, a covariance of 20 m, 30 a second;
- ``row1_own_reverse``: the same with sigma 5 m and a covariance of 1 mm;
- ``row1_relay``: drone_a's views of three floor tags forged (its system id), drone_a 20 m east,
  sigma 0.1 mm, a covariance of 20 m, 15 a second;
- ``row1b_relay``: drone_a's views of three floor tags forged, drone_a 2 m east, sigma 2 mm (what
  the sigma model makes consistent), stamped 1 ms after now, 15 a second;
- ``row2_relay``: drone_a's true view of its floor tag stamped 0.9 s in the future, every 0.9 s;
- ``row2_own``: the world camera's true view of drone_a's marker stamped 0.9 s ahead, every 0.9 s.

Printed per attack: what was sent, the node's counters that moved, the error at the autopilot
(mean, median, p95, RMSE, max) beside the clean run's, the autopilot's messages per second and the
reset counter's changes. Bars: RMSE within 10 % and max within 1 cm of the clean run's (rows 1 and 2,
over the frames both runs sent); for the relay drone (rows 1 and 1b) its worst error within the
speed bound times the attack's duration of the clean run's; 0 reset counter changes that no loss
explains (a change after less than 0.2 s without a message: a jump); autopilot messages per second
>= 95 % of the clean run's (row 2).

    python benchmarks/attack_peers.py [--seconds S] [--attacks a,b,...]
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import time

import numpy as np

from atlas_onboard.config import load_world
from atlas_onboard.sim import peerplay
from atlas_onboard.sim.command import autopilot_track
from atlas_onboard.sim.peerplay import LEADER_MARKER, LEADER_SENSOR, LEADER_SYSTEM_ID, WORLD_CAMERA
from atlas_onboard.sim.runner import WORLD_NODE_SYSTEM_ID
from atlas_onboard.sim.world import SimWorld

SECONDS = 8.0  # each run: the attack from START_S to TAIL_S before its end
START_S = 2.0
UNEXPLAINED_GAP_S = 0.2
TAIL_S = 0.5
HUGE = np.diag([400.0, 400.0, 400.0, 1.0, 1.0, 1.0])
TINY = np.diag([1e-6] * 6)
ATTACKS = ("row1_own", "row1_own_reverse", "row1_relay", "row1b_relay", "row2_relay", "row2_own")
INTERESTING = re.compile(
    r"^(rejected_|refused_from_|peer_observations|accepted$|reset_counter$|autopilot_sent|ambiguity_)"
)


def _attacker(name: str, node: peerplay.SoloNode) -> tuple[peerplay.Sender, str]:
    v = peerplay.views
    floor3 = lambda _t: (1, 3, 5)  # noqa: E731
    lead = lambda _t: (LEADER_MARKER,)  # noqa: E731
    if name == "row1_own":
        make = v(node, WORLD_CAMERA, lead, (20.0, 0, 0), 1e-4, HUGE)
        return peerplay.Sender(
            node, WORLD_NODE_SYSTEM_ID, 1 / 30, make
        ), "world camera: 20 m off, sigma 0.1 mm, cov 20 m"
    if name == "row1_own_reverse":
        make = v(node, WORLD_CAMERA, lead, (20.0, 0, 0), 5.0, TINY)
        return peerplay.Sender(node, WORLD_NODE_SYSTEM_ID, 1 / 30, make), "world camera: 20 m off, sigma 5 m, cov 1 mm"
    if name == "row1_relay":
        make = v(node, LEADER_SENSOR, floor3, (20.0, 0, 0), 1e-4, HUGE)
        return peerplay.Sender(node, LEADER_SYSTEM_ID, 1 / 15, make), "3 leader views: 20 m off, sigma 0.1 mm, cov 20 m"
    if name == "row1b_relay":
        make = v(node, LEADER_SENSOR, floor3, (2.0, 0, 0), 0.002, None, ahead_s=0.001)
        return peerplay.Sender(node, LEADER_SYSTEM_ID, 1 / 15, make), "3 leader views: 2 m off, sigma 2 mm, +1 ms"
    if name == "row2_relay":
        sim_world = SimWorld(node.scenario)
        make = v(node, LEADER_SENSOR, lambda t: (peerplay.nearest_floor_marker(sim_world, t),), ahead_s=0.9)
        return peerplay.Sender(node, LEADER_SYSTEM_ID, 0.9, make), "the leader's true view stamped 0.9 s ahead"
    if name == "row2_own":
        make = v(node, WORLD_CAMERA, lead, sigma_m=0.005, ahead_s=0.9)
        return peerplay.Sender(node, WORLD_NODE_SYSTEM_ID, 0.9, make), "the world camera's true view 0.9 s ahead"
    raise ValueError(name)


def one_run(setup: str, attack: str | None, seconds: float) -> dict:
    """One run of ``setup``'s node, attacked or not; the autopilot's track scored against the truth."""
    node = peerplay.start(setup, seconds)
    senders = []
    what = ""
    try:
        epoch = node.start_scenario()
        if setup == "relay":
            leader = peerplay.honest_leader(node)
            leader.run_between(epoch, epoch + seconds)
            senders.append(leader)
        if attack is not None:
            liar, what = _attacker(attack, node)
            liar.run_between(epoch + START_S, epoch + seconds - TAIL_S)
            senders.append(liar)
        time.sleep(max(0.0, epoch + seconds + 0.3 - time.time()))
    finally:
        for s in senders:
            s.join()
        code = node.stop()
    if code != 0:
        sys.exit(f"node exited with {code}: {node.log[-2000:]}")
    track = autopilot_track(node.autopilot.snapshot(), node.epoch_s)
    t0, t1 = START_S, seconds - TAIL_S
    inside = (track.arrival_s >= t0) & (track.arrival_s <= t1)
    p_true, _ = SimWorld(node.scenario).truth_series(node.entity, track.capture_s[inside])
    resets = track.reset_counter[inside]
    gaps = np.diff(track.arrival_s[inside])
    changed = np.diff(resets) != 0
    return {
        "what": what,
        "sent": senders[-1].sent if attack is not None else 0,
        "counters": node.final_counters(),
        "err_m": np.linalg.norm(track.p_m[inside] - p_true, axis=1),
        "capture_s": track.capture_s[inside],
        "lat_ms": (track.arrival_s[inside] - track.capture_s[inside]) * 1e3,
        "rate_hz": int(inside.sum()) / (t1 - t0),
        "resets": int(np.count_nonzero(changed)),
        # A change after less than the loss gap (edge_timeout 0.25 s, less the links' jitter) without a
        # message is no re-acquisition: a jump made it.
        "unexplained_resets": int(np.count_nonzero(changed & (gaps < UNEXPLAINED_GAP_S))),
        "duration_s": t1 - t0,
    }


def play(attacks: list[str], seconds: float, bars: list[tuple[str, float, str, float, bool]]) -> None:
    """Each attack against its setup's clean run (one per setup), printed; its bars appended to ``bars``."""
    from attack import matched, rms, summary, worst  # the harness imports this module: loaded here

    max_speed = load_world(_world_path()).fusion.max_speed_m_s
    cleans: dict[str, dict] = {}
    for attack in attacks:
        setup = attack.rsplit("_", 1)[1] if not attack.endswith("reverse") else "own"
        if setup not in cleans:
            cleans[setup] = one_run(setup, None, seconds)
            print(f"\n=== {setup} ({peerplay.SETUPS[setup]}): clean run, {seconds:g} s, scored {START_S:g}"
                  f" to {seconds - TAIL_S:g} s")  # fmt: skip
            print(f"  clean      {summary(cleans[setup])}  {cleans[setup]['rate_hz']:.1f} msg/s"
                  f" resets {cleans[setup]['resets']}")  # fmt: skip
        clean = cleans[setup]
        run = one_run(setup, attack, seconds)
        c = {k: v for k, v in run["counters"].items() if INTERESTING.match(k) and v}
        print(f"\n  {attack} on {setup}: {run['what']}; sent {run['sent']:,} observations")
        print(f"    counters: {' '.join(f'{k}={v}' for k, v in sorted(c.items()))}")
        print(f"    attack     {summary(run)}  {run['rate_hz']:.1f} msg/s resets {run['resets']}"
              f" (after no loss: {run['unexplained_resets']})")  # fmt: skip
        print(f"    clean      {summary(clean)}  {clean['rate_hz']:.1f} msg/s resets {clean['resets']}")
        e_attack, e_clean = matched(run, clean)
        print(f"    the {len(e_attack)} frames both runs sent, error cm: attack RMSE {rms(e_attack) * 100:5.2f}"
              f" max {worst(e_attack) * 100:5.2f}; clean RMSE {rms(e_clean) * 100:5.2f}"
              f" max {worst(e_clean) * 100:5.2f}")  # fmt: skip
        enough = len(e_attack) >= 10
        if attack.startswith(("row1_", "row2_")):
            ratio = rms(e_attack) / rms(e_clean) if enough else math.inf
            excess = (worst(e_attack) - worst(e_clean)) * 100 if enough else math.inf
            bars.append((f"rmse_ratio_{attack}", ratio, "x", 1.10, ratio <= 1.10))
            bars.append((f"max_excess_{attack}", excess, "cm", 1.0, excess <= 1.0))
        if setup == "relay" and attack.startswith("row1"):
            limit = max_speed * run["duration_s"]
            worst_m = float(run["err_m"].max()) if len(run["err_m"]) else math.inf
            excess_m = worst_m - float(clean["err_m"].max())
            bars.append((f"relay_worst_excess_{attack}", excess_m, "m", limit, excess_m <= limit))
        extra = run["unexplained_resets"]
        bars.append((f"reset_changes_by_peers_{attack}", extra, "count", 0, extra <= 0))
        if attack.startswith("row2_"):
            ratio = run["rate_hz"] / clean["rate_hz"] if clean["rate_hz"] > 0 else 0.0
            bars.append((f"autopilot_rate_{attack}", ratio, "x_clean", 0.95, ratio >= 0.95))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=SECONDS, help=f"length of each run (default {SECONDS:g})")
    ap.add_argument("--attacks", default=",".join(ATTACKS), help=f"comma-separated, of {', '.join(ATTACKS)}")
    args = ap.parse_args()
    attacks = [a for a in args.attacks.split(",") if a]
    if set(attacks) - set(ATTACKS):
        ap.error(f"unknown attacks: {', '.join(sorted(set(attacks) - set(ATTACKS)))}")
    bars: list[tuple[str, float, str, float, bool]] = []
    play(attacks, args.seconds, bars)
    print()
    for name, value, unit, limit, ok in bars:
        print(f"BAR {name} {value:.3f} {unit} {limit:g} {'pass' if ok else 'fail'}")
    return 0


def _world_path():
    from atlas_onboard.sim import scenarios

    return scenarios.get(peerplay.SCENARIO).world_path()


if __name__ == "__main__":
    sys.exit(main())
