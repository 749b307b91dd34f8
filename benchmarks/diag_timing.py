"""How much the same camera frame's pose differs between two clean runs: what attack.py's matched-frame
bars (RMSE within 10 %, max within 1 cm of the clean run's) measure when no attack is played.

attack.py scores an attacked run against a clean one over the camera frames whose pose reached the
autopilot in both: the frames and their detections are the same in every run. What a node does with
them may still depend on when things arrive (the autopilot's attitude samples, a leader's poses).
Here only clean runs are played, ``--runs`` of each setup: attack.py's own node (``own``: paper-test1's
drone, its simulator's camera path) and attack_peers' relay drone (``relay``: it sees only its
leader's marker). Per pair of runs, over their common frames: how many have the same error (within
1 um), the difference of the error |e_i - e_j| (mean, median, p95, max, cm), and what attack.py would
score for no attack, the max excess and the RMSE ratio. ``--no-attitude``: the simulated autopilot
sends no ATTITUDE (no gravity for the node), to tell that input's share.

Its bars, per setup: the largest max excess between two clean runs against attack.py's 1 cm, and the
largest RMSE ratio against its 1.10; a fail says those bars cannot tell an attack from the run's timing.

    python benchmarks/diag_timing.py [--runs 3] [--setups own,relay] [--no-attitude]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import attack
import attack_peers

from atlas_onboard.sim import solo

MAX_EXCESS_CM = 1.0  # attack.py's bars
RMSE_RATIO = 1.10
SAME_M = 1e-6


def clean_run(setup: str) -> dict:
    if setup == "own":
        return attack.one_run(None, 6.0, None, False)
    return attack_peers.one_run("relay", None, attack_peers.SECONDS)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="clean runs per setup (default 3, at least 2)")
    ap.add_argument("--setups", default="own,relay", help="own, relay or both (default both)")
    ap.add_argument("--no-attitude", action="store_true", help="the simulated autopilot sends no ATTITUDE")
    args = ap.parse_args()
    if args.runs < 2:
        ap.error("--runs must be at least 2")
    if args.no_attitude:  # start_solo (both setups') makes its autopilot through this name
        make = solo.SimAutopilot
        solo.SimAutopilot = lambda **kw: make(**{**kw, "attitude": None})  # type: ignore[misc]
    bars = []
    for setup in [s for s in args.setups.split(",") if s]:
        runs = [clean_run(setup) for _ in range(args.runs)]
        print(f"\n=== {setup}: {args.runs} clean runs{' without attitude' if args.no_attitude else ''}")
        for k, r in enumerate(runs):
            moved = {n: v for n, v in r["counters"].items() if n.startswith(("ambiguity_", "attitude_")) and v}
            print(f"  run {k}: {attack.summary(r)}  {r['rate_hz']:.1f} msg/s")
            print(f"         {' '.join(f'{n}={v}' for n, v in sorted(moved.items()))}")
        print("  runs  frames  same   |e_i - e_j| cm: mean median   p95   max   max excess cm  RMSE ratio")
        excess, ratios = [], []
        for i, j in itertools.permutations(range(args.runs), 2):
            a, b = attack.matched(runs[i], runs[j])
            if len(a) < 10:
                print(f"  {i},{j}  {len(a):6d}  (too few common frames)")
                continue
            d = np.abs(a - b) * 100
            excess.append((attack.worst(a) - attack.worst(b)) * 100)
            ratios.append(attack.rms(a) / attack.rms(b))
            if i < j:
                print(
                    f"  {i},{j}  {len(a):6d} {int(np.sum(d < SAME_M * 100)):5d}  {d.mean():18.3f} {np.median(d):6.3f}"
                    f" {np.percentile(d, 95):5.3f} {d.max():5.3f}   {excess[-1]:+6.3f} / {-excess[-1]:+6.3f}"
                    f"  {ratios[-1]:.3f} / {1 / ratios[-1]:.3f}"
                )
        worst_excess = max(excess, default=float("inf"))
        worst_ratio = max(ratios, default=float("inf"))
        bars.append((f"clean_max_excess_{setup}", worst_excess, "cm", MAX_EXCESS_CM, worst_excess <= MAX_EXCESS_CM))
        bars.append((f"clean_rmse_ratio_{setup}", worst_ratio, "x", RMSE_RATIO, worst_ratio <= RMSE_RATIO))
    print()
    for name, value, unit, limit, ok in bars:
        print(f"BAR {name} {value:.3f} {unit} {limit:g} {'pass' if ok else 'fail'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
