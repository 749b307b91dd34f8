"""The paper's method against each option of issue 7, from one simulated run per scenario and method.

Each run is the ordinary command line, ``atlas-onboard sim --scenario S --duration D --json --set
fusion.KEY=VALUE ...`` (real node processes, rendered cameras, simulated autopilots), and the table
shows what it reported against ground truth: position RMSE, max error, availability (and the
availability the geometry allows), and the mean position NEES of the covariance the node published
(consistent at about 3). Methods are sets of fusion overrides naming every key (so that no key of a
scenario's own file stays in force): ``paper`` is the paper's method (``fusion.method: paper``),
``default`` a world file's defaults, each other method one or more options on top of the paper's, and
``all`` every option together. The runs are made in this process, so that the cameras' images are
rendered once per scenario; the printed commands are what each run is.

Bars (one ``BAR name value unit limit pass|fail`` line each, computed from the runs; NaN and fail
when a run they need was not made or failed):
  ekf_rmse_ratio_paper_test1: RMSE of the EKF over the paper's, the paper-test1 drone; pass if < 1.
  ekf_availability_gain_gaps: availability of the EKF minus the paper's, gaps drone, points; pass if > 0.
  dijkstra_rmse_ratio_paths: RMSE of Dijkstra over BFS (the paper), the paths lead drone; pass if < 1.

    python benchmarks/compare_methods.py [--duration 20] [--scenarios a,b] [--methods paper,dijkstra]

The machine must keep up with the cameras in real time: run it on an otherwise idle machine (the
runs are one after another; each run's rates are in its JSON).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_onboard.config import PAPER_FUSION, FusionConfig

SCENARIOS = ("paper-test1", "paper-test2", "relay", "swarm", "paths", "gaps", "hard")


def _explicit(fusion: FusionConfig) -> dict[str, Any]:
    """Every key of a fusion section, so that no key of a scenario's own world file stays in force."""
    return {k: str(v) if isinstance(v, str) else v for k, v in asdict(fusion).items()}


PAPER: dict[str, Any] = _explicit(PAPER_FUSION)  # the paper's method (fusion.method: paper)
METHODS: dict[str, dict[str, Any]] = {
    "paper": PAPER,
    "default": _explicit(FusionConfig()),  # a world file's defaults, whatever the scenario's file sets
    "dijkstra": {**PAPER, "path": "dijkstra"},
    "inverse_variance": {**PAPER, "weighting": "inverse_variance"},
    "age": {**PAPER, "age_sigma_m_per_s": 1.0},
    "gate": {**PAPER, "outlier_gate_sigma": 5},
    "ekf": {**PAPER, "filter": "ekf"},
    "age_dijkstra": {**PAPER, "age_sigma_m_per_s": 1.0, "path": "dijkstra"},
    "ekf_age": {**PAPER, "filter": "ekf", "age_sigma_m_per_s": 1.0, "age_sigma_deg_per_s": 30.0},
    "all": {
        **PAPER,
        "path": "dijkstra",
        "weighting": "inverse_variance",
        "age_sigma_m_per_s": 1.0,
        "outlier_gate_sigma": 5,
        "filter": "ekf",
    },
    "all_deg": {
        **PAPER,
        "path": "dijkstra",
        "weighting": "inverse_variance",
        "age_sigma_m_per_s": 1.0,
        "age_sigma_deg_per_s": 30.0,
        "outlier_gate_sigma": 5,
        "filter": "ekf",
    },
}
# The entity each bar is about: the scenario's drone that the option is meant to help.
BAR_ENTITY = {"paper-test1": "ardrone", "gaps": "drone", "paths": "lead"}
SUMMARISE_OVER = 3  # scenarios with more scored entities get one summary row instead of one per entity


@dataclass
class Run:
    scenario: str
    method: str
    command: list[str]
    entities: list[dict[str, Any]] = field(default_factory=list)
    error: str = ""


def command_for(scenario: str, method: str, duration_s: float) -> list[str]:
    """The ``atlas-onboard sim`` command line of one run (as ``python -m atlas_onboard``)."""
    cmd = [sys.executable, "-m", "atlas_onboard", "sim", "--scenario", scenario, "--duration", f"{duration_s:g}"]
    cmd.append("--json")
    for key, value in METHODS[method].items():
        cmd += ["--set", f"fusion.{key}={value}"]
    return cmd


def run_one(scenario: str, method: str, duration_s: float) -> Run:
    """What the command line would run and print, run in this process so that every method of a
    scenario reuses the cameras' images rendered for its first run."""
    from atlas_onboard.sim.command import score_run
    from atlas_onboard.sim.runner import SimOptions
    from atlas_onboard.sim.runner import run as sim_run

    run = Run(scenario, method, command_for(scenario, method, duration_s))
    try:
        sim = sim_run(SimOptions(scenario=scenario, duration_s=duration_s, world_overrides={"fusion": METHODS[method]}))
        rep, _ = score_run(sim)
    except Exception as exc:  # a failed run is a row that says so
        run.error = f"{type(exc).__name__}: {exc}"
        return run
    run.entities = [asdict(e) for e in rep.entities]
    return run


def summary(entities: list[dict[str, Any]]) -> dict[str, Any]:
    """One row for many entities: RMSE and NEES over all their messages, the worst error, mean
    availabilities."""
    scored = [e for e in entities if e["messages"] > 0]
    n = sum(e["messages"] for e in scored)
    row = {"entity": f"all {len(entities)}", "messages": n}
    expected = _mean(e["expected_availability"] for e in entities)
    if not scored:
        nan = math.nan
        return {**row, "rmse_m": nan, "max_error_m": nan, "position_nees": nan, "availability": 0.0,
                "expected_availability": expected}  # fmt: skip
    nees = [(e["position_nees"], e["messages"]) for e in scored if math.isfinite(e["position_nees"])]
    return {
        **row,
        "rmse_m": math.sqrt(sum(e["rmse_m"] ** 2 * e["messages"] for e in scored) / n),
        "max_error_m": max(e["max_error_m"] for e in scored),
        "position_nees": sum(v * k for v, k in nees) / sum(k for _, k in nees) if nees else math.nan,
        "availability": _mean(e["availability"] for e in entities),
        "expected_availability": expected,
    }


def _mean(values: Any) -> float:
    v = list(values)
    return sum(v) / len(v) if v else math.nan


def table(runs: list[Run]) -> str:
    lines = [
        "| scenario | method | entity | position RMSE cm | max error cm | availability (expected) | position NEES |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for r in runs:
        if r.error:
            lines.append(f"| {r.scenario} | {r.method} | - | failed: {r.error} | | | |")
            continue
        rows = [summary(r.entities)] if len(r.entities) > SUMMARISE_OVER else r.entities
        for e in rows:
            lines.append(
                f"| {r.scenario} | {r.method} | {e['entity']} | {e['rmse_m'] * 100:.2f} | {e['max_error_m'] * 100:.2f}"
                f" | {e['availability']:.1%} ({e['expected_availability']:.1%}) | {e['position_nees']:.2f} |"
            )
    return "\n".join(lines)


def metric(runs: list[Run], scenario: str, method: str, key: str) -> float:
    for r in runs:
        if r.scenario == scenario and r.method == method and not r.error:
            for e in r.entities:
                if e["entity"] == BAR_ENTITY[scenario]:
                    return float(e[key])
    return math.nan


def bars(runs: list[Run]) -> list[str]:
    ekf = metric(runs, "paper-test1", "ekf", "rmse_m") / metric(runs, "paper-test1", "paper", "rmse_m")
    gain = (metric(runs, "gaps", "ekf", "availability") - metric(runs, "gaps", "paper", "availability")) * 100
    dij = metric(runs, "paths", "dijkstra", "rmse_m") / metric(runs, "paths", "paper", "rmse_m")
    return [
        f"BAR ekf_rmse_ratio_paper_test1 {ekf:.3f} ratio 1 {'pass' if ekf < 1 else 'fail'}",
        f"BAR ekf_availability_gain_gaps {gain:.1f} pts 0 {'pass' if gain > 0 else 'fail'}",
        f"BAR dijkstra_rmse_ratio_paths {dij:.3f} ratio 1 {'pass' if dij < 1 else 'fail'}",
    ]


def _names(text: str, known: tuple[str, ...] | list[str], what: str) -> list[str]:
    names = [n for n in text.split(",") if n]
    unknown = [n for n in names if n not in known]
    if unknown:
        raise SystemExit(f"--{what}: unknown {', '.join(unknown)} (choose from {', '.join(known)})")
    return names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, help="seconds per run (default 20)")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated (default: all six)")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated (default: all)")
    args = ap.parse_args(argv)
    scenarios = _names(args.scenarios, SCENARIOS, "scenarios")
    methods = _names(args.methods, list(METHODS), "methods")
    runs = []
    total = len(scenarios) * len(methods)
    for i, (scenario, method) in enumerate(((s, m) for s in scenarios for m in methods), start=1):
        print(f"[{i}/{total}] {scenario} {method} ...", file=sys.stderr, flush=True)
        t = time.monotonic()
        run = run_one(scenario, method, args.duration)
        print(
            f"[{i}/{total}] {scenario} {method}: {run.error or 'done'} ({time.monotonic() - t:.0f} s)", file=sys.stderr
        )
        runs.append(run)
    invocation = " ".join(shlex.quote(a) for a in ["python", "benchmarks/compare_methods.py", *(argv or sys.argv[1:])])
    print(f"Printed by `{invocation}`: one `atlas-onboard sim` run per scenario and method, {args.duration:g} s each.")
    print()
    print(table(runs))
    print()
    print("Commands (python -m atlas_onboard is the atlas-onboard command):")
    for r in runs:
        print("    " + " ".join(shlex.quote(a) for a in ["atlas-onboard", *r.command[3:]]))
    print()
    for line in bars(runs):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
