"""Rendered recordings of the simulator's ``map`` scenario (the mapping benchmark's flights)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import yaml

from atlas_onboard.config import load_world
from atlas_onboard.recording.format import RecordingWriter
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.camera import frames_path, prerender
from atlas_onboard.sim.scenario import Scenario
from atlas_onboard.sim.world import SimWorld


def world_doc(scenario: Scenario) -> dict:
    return yaml.safe_load(scenario.world_path().read_text(encoding="utf-8"))


def edit_marker(
    doc: dict, marker_id: int, *, move_m: tuple[float, float, float] | None = None, size_m: float | None = None
) -> dict:
    """A copy of a world document with one world marker moved or resized."""
    import copy

    out = copy.deepcopy(doc)
    for m in out["entities"]["world"]["markers"]:
        if m["id"] == marker_id:
            if move_m is not None:
                m["pose"]["pos"] = [float(a + b) for a, b in zip(m["pose"]["pos"], move_m, strict=True)]
            if size_m is not None:
                m["size_m"] = size_m
    return out


def record(
    scenario_name: str,
    doc: dict,
    sensor_ids: tuple[int, ...],
    duration_s: float,
    seed: int,
    out_dir: Path,
    detect: bool = True,
    start_s: float = 0.0,
) -> dict[int, Path]:
    """Render the scenario's cameras as the world ``doc`` has it and write one recording per sensor:
    ``duration_s`` from ``start_s`` into the scenario, each frame stamped with its scenario time (us)."""
    scenario = scenarios.get(scenario_name)
    at = f"-from{start_s:g}s" if start_s else ""  # a recording of another stretch is another recording
    done = {sid: out_dir / f"rec-{scenario.world().sensors[sid].entity}-s{seed}{at}" for sid in sensor_ids}
    if all((p / "index.jsonl").is_file() for p in done.values()):
        return done  # recorded by an earlier run (--keep)
    out_dir.mkdir(parents=True, exist_ok=True)
    world_file = out_dir / "truth-world.yaml"
    world_file.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    world = load_world(world_file)
    sim = SimWorld(scenario, world)
    paths = {}
    with tempfile.TemporaryDirectory(prefix="atlas-mapsim-") as tmp:
        prerender(scenario, world_file, seed, duration_s, Path(tmp), start_s)
        for sid in sensor_ids:
            sensor, intr = sim.cameras[sid]
            cal = intr.calibration()
            frames = np.load(frames_path(Path(tmp), sid), mmap_mode="r")
            fps = sensor.camera.fps
            T = sensor.T_entity_sensor
            p, q = T.translation, T.rotation.as_quat()
            det = None
            if detect:
                from atlas_onboard.detector.pipeline import Detector

                det = Detector(sensor, world, cal, decimate=2.0)
            rec = done[sid]
            writer = RecordingWriter(
                rec,
                cal,
                sensor_name=sensor.name,
                sensor_id=sid,
                entity=sensor.entity,
                p_body_camera_m=tuple(p),
                q_body_camera_wxyz=(q[3], q[0], q[1], q[2]),
            )
            n = int(duration_s * fps)
            first = round(start_s * fps)
            for j in range(n):
                t = (first + j) / fps
                stamp = round(t * 1e6)
                gray = np.array(frames[j])
                x, y, z, w = sim.truth(t, {sensor.entity})[sensor.entity].rotation.as_quat()
                markers = det.detect(gray, stamp) if det is not None else []
                writer.write(gray, stamp, markers, (w, x, y, z))
            writer.close()
            paths[sid] = rec
    return paths
