"""A world file with one marker moved by 10 cm (issue 19), without processes or clocks: deterministic.

The frames are rendered from the true world and run through the real detector, listener and graph with
the nodes' world file (marker 2 moved 10 cm along x) by :func:`atlas_onboard.sim.offline.run`, from the
scenario's start; the anchor is the same frames with the true world file. A live run on a loaded machine
drops frames, which moves its availability by more than a measured place does; this one does not.

Per world: the drone's output messages, position error mean, median and p95 per state (``view``: a tag
fully in view at that frame; ``blind``: none), availability against the time a tag is fully in view (``cover``,
as bench_hard scores it, from the ideal frames after the warm-up; an output counts at its capture time),
position RMSE and max (mm), share within 3 sigma per axis, pose NEES; the frames with a tag in view and
no output; the measured places established, with their error against the true marker pose in their own
sigmas (NEES over 6); and the "moved" verdicts (none may name a marker in the anchor).

    python benchmarks/bench_moved_offline.py [--scenario hard-near,hard] [--duration 30]
"""

from __future__ import annotations

import argparse
import copy
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_onboard.config.read_world import parse_world
from atlas_onboard.core import places as places_module
from atlas_onboard.core.refine import residuals
from atlas_onboard.detector import pipeline
from atlas_onboard.sim import camera, offline, report, scenarios
from atlas_onboard.sim.runner import WARMUP_S
from atlas_onboard.sim.world import FRESH_S, SimWorld

ENTITY = "drone"
MOVED_MARKER = 2  # as bench_hard
MOVED_BY_M = (0.10, 0.0, 0.0)


@dataclass
class Run:
    name: str
    output_s: list[float] = field(default_factory=list)
    errors: offline.StageErrors | None = None
    lost_s: list[float] = field(default_factory=list)
    places: list[tuple[float, int, float, float, int]] = field(default_factory=list)  # t, id, NEES6, mm, views
    moved_lines: list[str] = field(default_factory=list)
    cover: float = float("nan")


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def moved_world(scenario: str):
    doc = yaml.safe_load(scenarios.get(scenario).world_path().read_text(encoding="utf-8"))
    doc = copy.deepcopy(doc)
    for m in doc["entities"]["world"]["markers"]:
        if m["id"] == MOVED_MARKER:
            m["pose"]["pos"] = [float(a) + b for a, b in zip(m["pose"]["pos"], MOVED_BY_M, strict=True)]
    return parse_world(doc)


def run_world(scenario: str, name: str, world, frames: int) -> Run:
    """The offline estimator on the scenario's frames (rendered from the true world) with ``world`` as the
    nodes' world file; the output times come from the detector's capture stamps (one camera: each output
    is the frame just detected)."""
    run = Run(name)
    true_world = scenarios.get(scenario).world()
    now = [0.0]
    orig_detect, orig_add = pipeline.Detector.detect, offline.StageErrors.add
    orig_renderer = camera.FrameRenderer
    orig_establish = places_module.MeasuredPlaces.establish
    adds: list[tuple[int, float]] = []

    def detect(self, image, capture_time_us, *a, **k):
        out = orig_detect(self, image, capture_time_us, *a, **k)
        now[0] = capture_time_us / 1e6
        return out

    def add(self, e, C, t_s=float("nan")):
        n = len(self.errors)
        orig_add(self, e, C, t_s)
        if len(self.errors) > n:  # (one not positive definite is counted, not kept)
            adds.append((id(self), now[0]))

    def establish(self, marker_id, now_us, trusted):
        had = self.place(marker_id)
        got = orig_establish(self, marker_id, now_us, trusted)
        if had is None and isinstance(got, places_module.MeasuredPlace):
            T = true_world.markers[marker_id].T_entity_marker
            e = residuals(got.p_world_marker_m[None], got.R_world_marker[None], T.translation,
                          T.rotation.as_matrix())[0]  # fmt: skip
            nees = float(e @ np.linalg.solve(got.cov, e))
            run.places.append((now_us / 1e6, marker_id, nees, float(np.linalg.norm(e[:3])) * 1e3, got.views))
        return got

    lines = _Lines()
    logging.getLogger("atlas_onboard").addHandler(lines)
    pipeline.Detector.detect = detect
    offline.StageErrors.add = add
    places_module.MeasuredPlaces.establish = establish
    camera.FrameRenderer = lambda sc, _w, s, seed: orig_renderer(sc, true_world, s, seed)
    try:
        _, outs = offline.run(scenario, frames, world=world, start_s=0.0)
    finally:
        pipeline.Detector.detect, offline.StageErrors.add = orig_detect, orig_add
        places_module.MeasuredPlaces.establish = orig_establish
        camera.FrameRenderer = orig_renderer
        logging.getLogger("atlas_onboard").removeHandler(lines)
    out = outs[ENTITY]
    run.errors = out
    run.output_s = [t for k, t in adds if k == id(out)]
    run.moved_lines = [line for line in lines.lines if "has moved" in line]
    return run


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="hard-near,hard")
    ap.add_argument("--duration", type=float, default=30.0)
    args = ap.parse_args(argv)
    bars: list[str] = []
    for scenario in args.scenario.split(","):
        sim_world = SimWorld(scenarios.get(scenario))
        fps = 1.0 / sim_world.frame_period_s()
        frames = round(args.duration * fps)
        t1 = (frames - 1) / fps
        ideal = sim_world.visible_frames(ENTITY, t1)
        runs = [
            run_world(scenario, "anchor", scenarios.get(scenario).world(), frames),
            run_world(scenario, "moved", moved_world(scenario), frames),
        ]
        print(f"scenario {scenario}: {frames} frames; marker {MOVED_MARKER} moved by {MOVED_BY_M} m in 'moved'")
        print(f"{'world':<8} {'msgs':>5} {'cover%':>7} {'RMSE mm':>8} {'max mm':>7} {'3s x%':>6} {'3s y%':>6}"
              f" {'3s z%':>6} {'NEES6':>6} {'lost':>5}")  # fmt: skip
        for r in runs:
            assert r.errors is not None
            out_s = np.array(r.output_s)
            r.cover = report.coverage(out_s, ideal, WARMUP_S, t1, FRESH_S) * 100
            in_view = set(np.round(ideal[ideal >= WARMUP_S], 3))
            r.lost_s = sorted(t for t in in_view if t not in set(np.round(out_s, 3)))
            e = np.array(r.errors.errors)
            norms = np.linalg.norm(e[:, :3], axis=1) * 1e3
            w3 = r.errors.within_3_sigma() * 100
            nees6 = float(np.mean(r.errors.nees()))
            print(f"{r.name:<8} {len(e):>5} {r.cover:>7.2f} {r.errors.rmse_m() * 1e3:>8.2f} {norms.max():>7.1f}"
                  f" {w3[0]:>6.1f} {w3[1]:>6.1f} {w3[2]:>6.1f} {nees6:>6.2f} {len(r.lost_s):>5}")  # fmt: skip
            r_max = float(norms.max())
            k = int(np.argmax(norms))
            print(f"  {r.name}: max at {r.output_s[k]:.3f} s; frames with a tag in view and no output:"
                  f" {' '.join(f'{t:.3f}' for t in r.lost_s[:40]) or 'none'}")  # fmt: skip
            ideal_set = set(np.round(ideal, 3))
            view = np.array([round(t, 3) in ideal_set for t in r.output_s], dtype=bool)
            for state, sel in (("all", np.ones(len(norms), bool)), ("view", view), ("blind", ~view)):
                v = norms[sel]
                figs = f"{v.mean():.2f} {np.median(v):.2f} {np.percentile(v, 95):.2f}" if len(v) else "nan nan nan"
                print(f"  {r.name} {state:<5} n {len(v):>4}  mean median p95 (mm): {figs}")
            for t, mid, nees, mm, views in r.places:
                print(f"  {r.name}: marker {mid} placed at {t:.3f} s from {views} views: {mm:.2f} mm off,"
                      f" NEES6 {nees:.2f}")  # fmt: skip
            print(f"  {r.name}: {len(r.moved_lines)} 'has moved' log line(s)"
                  + "".join(f"\n    {line}" for line in r.moved_lines[:3]))  # fmt: skip
            if r.name == "moved":
                bars += [
                    f"BAR {scenario}:moved.cover {r.cover:.2f} % 99 {'pass' if r.cover >= 99 else 'fail'}",
                    f"BAR {scenario}:moved.max {r_max:.1f} mm 30 {'pass' if r_max <= 30 else 'fail'}",
                    f"BAR {scenario}:moved.rmse {r.errors.rmse_m() * 1e3:.2f} mm 5"
                    f" {'pass' if r.errors.rmse_m() <= 0.005 else 'fail'}",
                    f"BAR {scenario}:moved.within3_min {w3[:3].min():.2f} % 99"
                    f" {'pass' if w3[:3].min() >= 99 else 'fail'}",
                    f"BAR {scenario}:moved.named {len(r.moved_lines)} lines 1 {'pass' if r.moved_lines else 'fail'}",
                ]
            else:
                n = len(r.moved_lines)
                bars.append(f"BAR {scenario}:anchor.false_moved {n} lines 0 {'pass' if n == 0 else 'fail'}")
        a, m = runs
        print(f"  moved / anchor: cover {m.cover / a.cover:.4f}, RMSE {m.errors.rmse_m() / a.errors.rmse_m():.2f}")
    for line in bars:
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
