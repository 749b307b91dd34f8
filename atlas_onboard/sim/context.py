"""The simulation a node process belongs to: the scenario, seed and start time the runner hands it in the
``ATLAS_SIM`` environment variable (JSON: scenario, seed, epoch_file, duration_s, frames_dir, geometric,
replay, flights_dir), and the run's clock on which its simulated sensors tick."""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.scenario import Scenario

SIM_ENV = "ATLAS_SIM"


@dataclass(frozen=True)
class SimContext:
    """The simulation a node belongs to."""

    scenario: Scenario
    seed: int
    epoch_file: Path
    duration_s: float
    frames_dir: Path | None = None  # the cameras' pre-rendered images, if the runner made them
    geometric: bool = False  # no images: corners from the geometry plus noise
    replay: str = ""  # a replay mode: the cameras read the frames' image folders (sim.camera.replay_folder)

    @classmethod
    def from_env(cls) -> SimContext:
        raw = os.environ.get(SIM_ENV)
        if not raw:
            raise AtlasError(
                f"camera source 'sim' needs the {SIM_ENV} environment variable: run it from `atlas-onboard sim`"
            )
        try:
            doc = json.loads(raw)
            scenario = scenarios.get(doc["scenario"])
            if doc.get("flights_dir"):  # the flown entities' truth, written by the runner as the run goes
                scenario = scenario.with_flights(Path(doc["flights_dir"]))
            return cls(
                scenario,
                int(doc.get("seed", 0)),
                Path(doc["epoch_file"]),
                float(doc["duration_s"]),
                Path(doc["frames_dir"]) if doc.get("frames_dir") else None,
                bool(doc.get("geometric", False)),
                str(doc.get("replay") or ""),
            )
        except (ValueError, KeyError, TypeError) as exc:
            raise AtlasError(f"{SIM_ENV}: expected JSON with scenario, epoch_file and duration_s ({exc})") from None

    def wait_epoch(self, stop: threading.Event) -> float | None:
        """The run's start time (UNIX s), waiting for the runner to write it; None if stopped first."""
        while not stop.is_set():
            try:
                return float(self.epoch_file.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                stop.wait(0.02)
        return None

    def ticks(
        self, stop: threading.Event, period_s: float, on_late: Callable[[int], None] | None = None
    ) -> Iterator[tuple[float, int, float]]:
        """The run's clock for a periodic sensor: ``(epoch, k, t)`` for k = 0, 1, ..., each yielded when
        the wall clock reaches ``epoch + t`` (t = k period_s, s from the run's start), until ``stop``.
        With ``on_late``, ticks whose time passed more than a period ago are dropped, never queued,
        and their number handed to it."""
        epoch = self.wait_epoch(stop)
        if epoch is None:
            return
        k = 0
        while not stop.is_set():
            t = k * period_s
            wait = epoch + t - time.time()
            if wait > 0:
                stop.wait(wait)
                continue
            if on_late is not None and wait < -period_s:
                missed = int(-wait / period_s)
                on_late(missed)
                k += missed
                continue
            yield epoch, k, t
            k += 1
