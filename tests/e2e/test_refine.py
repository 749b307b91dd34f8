"""End to end over 127.0.0.1 (live map refinement): two drones' node processes replay their
simulated cameras (the ``map`` scenario, recorded once) and share their observations over MAVLink; their
world file has one marker 10 cm from where it is.

- ``on``: both refine (``nodes.defaults.refine``) and write the refined world file at exit
  (``--write-map``); their link is signed (a peer's observations are evidence only on signed
  links). This flight shows the marker with two or more others in about 11 to 14 views
  (images 0.5 s apart, its own and its peer's) to each node, around the 12 a move needs: a node that
  has them places the marker where it truly is, within a few mm, logs, counts and announces it once;
  one that has not leaves it as it was and says why. At least one of the two has them, and neither
  moves any other marker;
- ``off``: mapper1's flight without the setting: nothing is refined, said or written.
"""

from __future__ import annotations

import copy
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from atlas_onboard.config import load_world
from atlas_onboard.sim import recordings, scenarios
from atlas_onboard.sim.autopilot import SimAutopilot
from tests.e2e.helpers import NodeProcess, free_udp_port, wait_for, write_world

SCENARIO = "map"
SENSORS = {1: "mapper1", 2: "mapper2"}
START_S, DURATION_S = 44.0, 10.0  # both cameras see marker 2 with others here (until about 50 s)
MOVED_ID, MOVE_M = 2, (0.1, 0.0, 0.0)
FPS = 5  # a slow camera: a loaded machine's detector keeps up with it (refinement counts views 0.5 s apart)
BOUND_M = 0.005  # the refined marker within this of the truth: a few times the detections' noise at 1-2 m


@dataclass
class Run:
    log: str
    counters: dict[str, int]
    statustexts: list[bytes]
    written: Path


def _node_doc(doc: dict, recs: dict[int, Path], port: int, aps: dict[str, int], refine: bool, key: Path) -> dict:
    d = copy.deepcopy(doc)
    for sid, entity in SENSORS.items():
        for s in d["entities"][entity]["sensors"]:
            if s["id"] == sid:  # the recording carries its calibration
                # Every frame, stamped by the recording: the views the refinement counts do not depend on
                # how loaded the machine is (realtime replay drops frames and left a drone a view short).
                s["camera"] = {"source": str(recs[sid]), "replay": "every_frame", "fps": FPS}
    signing = {"key_file": str(key), "require": True}
    links = {
        "mapper1": {"url": f"udpin:127.0.0.1:{port}", "signing": signing},
        "mapper2": {"url": f"udpout:127.0.0.1:{port}", "signing": signing},
    }
    d["nodes"] = {
        e: {
            "system_id": k,
            "autopilot": {"url": f"udpout:127.0.0.1:{aps[e]}"},
            "peers": [links[e]],
        }
        for k, e in ((1, "mapper1"), (2, "mapper2"))
    }
    if refine:
        # Every image with three or more world markers gives evidence (the short flight needs all of it).
        d["nodes"]["defaults"] = {"refine": {"per_marker_period_s": 0}}
    return d


@pytest.fixture(scope="module")
def truth_and_runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict[str, dict[str, Run]]]:
    out = tmp_path_factory.mktemp("refine")
    doc = recordings.world_doc(scenarios.get(SCENARIO))
    for entity in SENSORS.values():
        for sensor in doc["entities"][entity]["sensors"]:
            sensor["camera"]["fps"] = FPS
    recs = recordings.record(SCENARIO, doc, tuple(SENSORS), DURATION_S, 1, out, detect=False, start_s=START_S)
    moved = recordings.edit_marker(doc, MOVED_ID, move_m=MOVE_M)
    key = out / "swarm.key"
    key.write_bytes(os.urandom(32))
    key.chmod(0o600)
    started = {}
    try:
        for name in ("on", "off"):
            (out / name).mkdir()
            aps = {e: SimAutopilot(system_id=k).start() for k, e in SENSORS.items()}
            ports = {e: a.port for e, a in aps.items()}
            path = write_world(out / name, _node_doc(moved, recs, free_udp_port(), ports, name == "on", key))
            # off: mapper1 alone, which is all it needs to show, at less CPU
            entities = ("mapper1", "mapper2") if name == "on" else ("mapper1",)
            nodes = {}
            for e in entities:
                args = ("--write-map", str(out / name / f"refined-{e}.yaml")) if name == "on" else ()
                nodes[e] = NodeProcess(path, e, args=args)
            started[name] = (aps, nodes)
        for _, nodes in started.values():
            for node in nodes.values():
                assert wait_for(lambda node=node: "end of" in node.log(), timeout=120), node.log()[-3000:]
        runs: dict[str, dict[str, Run]] = {}
        for name, (aps, nodes) in started.items():
            runs[name] = {}
            for e, node in nodes.items():
                assert node.stop() == 0
                written = out / name / f"refined-{e}.yaml"
                runs[name][e] = Run(node.log(), node.final_counters(), list(aps[e].statustexts), written)
        return doc, runs
    finally:
        for aps, nodes in started.values():
            for node in nodes.values():
                node.stop()
            for ap in aps.values():
                ap.stop()


def _positions(path: Path) -> dict[int, np.ndarray]:
    return {m.id: m.T_entity_marker.translation for m in load_world(path).entity("world").markers}


def test_the_misplaced_marker_is_refined_to_where_it_is(truth_and_runs, tmp_path) -> None:
    doc, runs = truth_and_runs
    truth_file = tmp_path / "truth.yaml"
    truth_file.write_text(yaml.safe_dump(doc, sort_keys=False))
    truth = _positions(truth_file)
    refined_by = []
    for entity, run in runs["on"].items():
        assert run.written.is_file(), run.log[-3000:]
        assert run.counters["peer_observations"] > 0 and run.counters["refine_evidence"] > 0
        written = _positions(run.written)
        given = _positions(run.written.parent / "world.yaml")
        # Every other marker is written exactly as the (moved) input has it: nothing else was refined.
        for mid, p in written.items():
            if mid != MOVED_ID:
                np.testing.assert_allclose(p, given[mid], atol=1e-5)
        if run.counters["refine_markers_refined"] == 0:  # not enough views yet: left as it is, and said why
            np.testing.assert_allclose(written[MOVED_ID], given[MOVED_ID], atol=1e-5)
            assert re.search(rf"id: {MOVED_ID},.*# kept: .*not refined: \d+ independent views", run.written.read_text())
            continue
        refined_by.append(entity)
        err = np.linalg.norm(written[MOVED_ID] - truth[MOVED_ID])
        assert err < BOUND_M, (entity, written[MOVED_ID], truth[MOVED_ID], run.log[-3000:])
        assert re.search(rf"id: {MOVED_ID},.*# refined: 1-sigma position \[[\d., ]+\] mm", run.written.read_text())
        # Logged, counted, announced once.
        assert f"world marker {MOVED_ID} refined: " in run.log and f"world marker {MOVED_ID} being refined" in run.log
        assert run.counters["refine_markers_refined"] == 1 and run.counters["refine_updates"] >= 2  # 5 cm steps
        texts = [t for t in run.statustexts if b"refined" in t]
        assert len(texts) == 1 and f"marker {MOVED_ID} refined -10".encode() in texts[0], run.statustexts
    kept = {e: [x for x in r.written.read_text().splitlines() if "kept" in x] for e, r in runs["on"].items()}
    assert refined_by, kept


def test_without_the_setting_nothing_is_refined(truth_and_runs) -> None:
    _, runs = truth_and_runs
    run = runs["off"]["mapper1"]
    assert "refined" not in run.log
    assert not any(k.startswith("refine_") for k in run.counters)
    assert not any(b"refined" in t for t in run.statustexts)
    assert not run.written.exists()
