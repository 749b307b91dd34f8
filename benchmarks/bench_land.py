"""Precision landing: touchdown error on a static pad and on a moving rover, and no stale LANDING_TARGET.

Each run is closed loop and faster than real time (atlas_onboard/sim/landing.py): the simulator's
geometric detections go through the node's listener, graph, landing decision and LANDING_TARGET
builder (the code a node runs) to the simulated autopilot's lander, which flies the drone.

- touchdown error (cm, horizontal, against the true landing point), 10 runs per scenario and form: the
  scenario's own form is the bar's (land-pad: PX4, land-rover: ArduPilot, whose filter follows a moving
  target); the other form is printed beside it;
- the target lost for 2 s mid-descent (every camera hidden from 1.5 s to 3.5 s), 10 runs per scenario:
  LANDING_TARGET messages sent whose newest observation was older than max_age_s, beside the anchor (a
  sender that repeats its last target at rate_hz).

CPU time per run (process_time) is printed; pin the process for steady figures:

    taskset -c 1 python benchmarks/bench_land.py [--runs 10]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from atlas_onboard.sim import scenarios
from atlas_onboard.sim.landing import run

# The landing scenarios and the form each is flown in by default.
LANDINGS = {n: sc.landing.form for n, sc in scenarios.SCENARIOS.items() if sc.landing is not None}

BARS = (("landing_static_cm", "land-pad", 3.0), ("landing_moving_cm", "land-rover", 8.0))
GAP_S = (1.5, 3.5)


def stats(values: list[float]) -> str:
    v = np.asarray(values, dtype=float)
    return (f"mean {v.mean():7.2f}  median {np.median(v):7.2f}  p95 {np.percentile(v, 95):7.2f}"
            f"  max {v.max():7.2f}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    args = parser.parse_args(argv)
    means: dict[str, float] = {}
    print(f"touchdown error, cm, {args.runs} runs (seeds 0-{args.runs - 1}); the scenario's form first")
    for name, own_form in LANDINGS.items():
        forms = [own_form] + [f for f in ("px4", "ardupilot") if f != own_form]
        for form in forms:
            errors, cpu, missed = [], [], 0
            for seed in range(args.runs):
                t0 = time.process_time()
                r = run(name, seed=seed, form=form)
                cpu.append(time.process_time() - t0)
                if r.touchdown_error_m is None:
                    missed += 1
                    continue
                errors.append(100.0 * r.touchdown_error_m)
            if form == own_form:
                means[name] = float(np.mean(errors)) if errors and not missed else float("inf")
            tag = "bar " if form == own_form else "also"
            print(f"  {tag} {name:10s} {form:9s} {stats(errors) if errors else 'no touchdown'}"
                  f"  not landed {missed}  cpu/run {np.mean(cpu):.2f} s")  # fmt: skip
    print(f"target lost {GAP_S[0]}-{GAP_S[1]} s mid-descent, {args.runs} runs per scenario (its own form)")
    stale_total = 0
    for name in LANDINGS:
        sent, stale, held, aborts, errors = 0, 0, 0, 0, []
        for seed in range(args.runs):
            r = run(name, seed=100 + seed, gap_s=GAP_S)
            sent, stale, held, aborts = sent + r.sent, stale + r.stale_sent, held + r.held_stale, aborts + r.aborts
            if r.touchdown_error_m is not None:
                errors.append(100.0 * r.touchdown_error_m)
        stale_total += stale
        print(f"  {name:10s} sent {sent:4d}  stale sent {stale:3d}  (anchor, last target repeated at rate_hz:"
              f" {held:4d} stale)  aborts {aborts:2d}  landed {len(errors)}/{args.runs}"
              f"  touchdown {stats(errors) if errors else '-'} cm")  # fmt: skip
    for bar, name, limit in BARS:
        value = means[name]
        print(f"BAR {bar} {value:.2f} cm {limit:g} {'pass' if value <= limit else 'fail'}")
    print(f"BAR stale_landing_targets {stale_total} messages 0 {'pass' if stale_total == 0 else 'fail'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
