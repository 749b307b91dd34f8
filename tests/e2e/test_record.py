"""End to end over 127.0.0.1: node processes replay a simulated flight's recording (its
frames at their recorded capture stamps) to simulated autopilots, at the same time:

- ``plain``: the poses are the recorded flight's truth, and nothing is reported moved;
- ``record``: ``run --record DIR`` records the camera as it flies, and sends the same poses;
- ``cap``: a 1 MB cap stops the recording early (said once); the node flies on;
- ``unwritable``: a record directory that cannot be made is one line; the node flies on;
- ``moved``: a world file with one marker 10 cm off: that marker is named, with its offset.
"""

from __future__ import annotations

import copy
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from atlas_onboard.config import load_world
from atlas_onboard.recording.format import read_frames
from atlas_onboard.sim import recordings, scenarios
from atlas_onboard.sim.autopilot import Received, SimAutopilot
from atlas_onboard.sim.world import SimWorld
from tests.e2e.helpers import NodeProcess, wait_for, write_world

SCENARIO, SENSOR, ENTITY = "map", 1, "mapper1"
START_S, DURATION_S = 8.0, 2.0  # a stretch of the flight where the camera sees three or more markers
MOVED_ID, MOVE_M = 17, (0.1, 0.0, 0.0)
CAP_MB = 1.0
SCHEDULING_SLACK = 2  # poses (of 30 frames) that two frames reaching the loop together may cost a run


@dataclass
class Run:
    world_file: Path
    log: str
    counters: dict[str, int]
    poses: list[Received]
    statustexts: list[bytes]
    code: int
    record_dir: Path | None

    @property
    def shift_us(self) -> int:
        """How far the replay shifted the recorded capture stamps (the node logs it)."""
        m = re.search(r"recorded capture stamps shifted by ([+-]\d+) us", self.log)
        assert m, self.log[-3000:]
        return int(m.group(1))


def _node_doc(doc: dict, recording: Path, autopilot_port: int) -> dict:
    d = copy.deepcopy(doc)
    for s in d["entities"][ENTITY]["sensors"]:
        if s["id"] == SENSOR:  # the recording carries its calibration
            s["camera"] = {"source": str(recording), "replay": "every_frame", "fps": 15}
    d["nodes"] = {ENTITY: {"system_id": 1, "autopilot": {"url": f"udpout:127.0.0.1:{autopilot_port}"}}}
    return d


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("flight")
    doc = recordings.world_doc(scenarios.get(SCENARIO))
    rec = recordings.record(SCENARIO, doc, (SENSOR,), DURATION_S, 1, out, detect=False, start_s=START_S)
    return doc, rec[SENSOR]


@pytest.fixture(scope="module")
def runs(flight: tuple[dict, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Run]:
    doc, rec = flight
    base = tmp_path_factory.mktemp("runs")
    blocker = base / "a-file"
    blocker.write_text("not a directory")
    plans = {
        "plain": (doc, (), None),
        "record": (doc, ("--record", str(base / "rec-record")), base / "rec-record"),
        "cap": (doc, ("--record", str(base / "rec-cap"), "--record-max-mb", str(CAP_MB)), base / "rec-cap"),
        "unwritable": (doc, ("--record", str(blocker / "rec")), None),
        "moved": (recordings.edit_marker(doc, MOVED_ID, move_m=MOVE_M), (), None),
    }
    started = {}
    try:
        for name, (d, args, record_dir) in plans.items():
            ap = SimAutopilot(system_id=1).start()
            (base / name).mkdir()
            path = write_world(base / name, _node_doc(d, rec, ap.port))
            started[name] = (ap, NodeProcess(path, ENTITY, args=args), path, record_dir)
        for _, node, _, _ in started.values():
            assert wait_for(lambda node=node: "end of" in node.log(), timeout=120), node.log()[-3000:]
        wait_for(lambda: False, timeout=0.5)  # the last frames' poses on their way
        out = {}
        for name, (ap, node, path, record_dir) in started.items():
            code = node.stop()
            poses = [m for m in ap.snapshot() if m.kind == "VISION_POSITION_ESTIMATE"]
            out[name] = Run(path, node.log(), node.final_counters(), poses, list(ap.statustexts), code, record_dir)
        return out
    finally:
        for ap, node, _, _ in started.values():
            node.stop()
            ap.stop()


def test_a_replayed_recording_gives_the_recorded_flight(runs: dict[str, Run], flight: tuple[dict, Path]) -> None:
    run = runs["plain"]
    assert run.code == 0
    frames = list(read_frames(flight[1], with_images=False))
    assert run.counters["camera_cam_frames"] == len(frames)  # every frame, in order
    world = load_world(run.world_file)
    sim = SimWorld(scenarios.get(SCENARIO), world)
    recorded_us = {f.capture_time_us for f in frames}
    err_m = []
    for m in run.poses:
        stamp_us = m.usec - run.shift_us
        assert stamp_us in recorded_us  # stamped by the recorded capture stamps, shifted
        p_enu = sim.truth(stamp_us / 1e6, {ENTITY})[ENTITY].translation
        truth_ned = np.array([p_enu[1], p_enu[0], -p_enu[2]])
        err_m.append(np.linalg.norm(np.array(m.xyz_m) - truth_ned))
    err_m = np.array(err_m)
    # Most frames give a pose (some see a lone marker at a grazing angle and are refused).
    assert len(run.poses) >= 0.8 * len(frames), (len(run.poses), len(frames))
    assert np.median(err_m) < 0.01 and err_m.max() < 0.05, np.sort(err_m)[-5:]
    # The true world file: no marker is reported moved.
    assert "has moved" not in run.log and run.counters.get("camera_cam_detector_markers_moved", 0) == 0
    assert not any(b"moved" in t for t in run.statustexts), run.statustexts


def test_recording_as_it_flies_changes_no_output(runs: dict[str, Run], flight: tuple[dict, Path]) -> None:
    plain, run = runs["plain"], runs["record"]
    assert run.code == 0
    c = run.counters
    # The same frames detected and accepted, and as many poses sent (two frames that reach the loop
    # together give one pose: on a loaded machine that may happen to a frame or two in either run).
    assert c["camera_cam_frames"] == plain.counters["camera_cam_frames"] == len(list(read_frames(flight[1], False)))
    assert c["accepted"] == plain.counters["accepted"] > 0
    assert c["autopilot_sent"] == len(run.poses) >= len(plain.poses) - SCHEDULING_SLACK
    # What was recorded: every frame detected (or counted as dropped), bit for bit, at its stamp.
    assert run.record_dir is not None
    (rec,) = list(run.record_dir.iterdir())
    got = list(read_frames(rec))
    assert len(got) == c["camera_cam_record_written"] > 0
    assert c["camera_cam_record_written"] + c["camera_cam_record_dropped_queue_full"] == c["camera_cam_frames"]
    source = {f.capture_time_us: f.gray for f in read_frames(flight[1])}
    for f in got:
        assert np.array_equal(f.gray, source[f.capture_time_us - run.shift_us])
    assert sum(len(f.markers) for f in got) > 0  # the node's MarkerData with its frames


def test_a_size_cap_stops_the_recording_and_the_node_flies_on(runs: dict[str, Run]) -> None:
    plain, run = runs["plain"], runs["cap"]
    assert run.code == 0
    c = run.counters
    assert c["accepted"] == plain.counters["accepted"]
    assert c["autopilot_sent"] >= plain.counters["autopilot_sent"] - SCHEDULING_SLACK
    assert run.record_dir is not None
    (rec,) = list(run.record_dir.iterdir())
    used = sum(p.stat().st_size for p in rec.rglob("*") if p.is_file())
    assert used <= CAP_MB * 1e6
    assert 0 < c["camera_cam_record_written"] < c["camera_cam_frames"]
    not_written = c["camera_cam_frames"] - c["camera_cam_record_written"]
    assert c["camera_cam_record_dropped_cap"] == not_written - c["camera_cam_record_dropped_queue_full"]
    assert run.log.count("reached its cap") == 1


def test_an_unwritable_record_directory_is_one_line_and_the_node_flies_on(runs: dict[str, Run]) -> None:
    plain, run = runs["plain"], runs["unwritable"]
    assert run.code == 0
    assert run.counters["accepted"] == plain.counters["accepted"]
    assert run.counters["autopilot_sent"] >= plain.counters["autopilot_sent"] - SCHEDULING_SLACK
    lines = [x for x in run.log.splitlines() if "not recorded" in x and "cannot write" in x]
    assert len(lines) == 1, run.log[-3000:]
    assert "Traceback" not in run.log


def test_a_moved_marker_is_named_with_its_offset(runs: dict[str, Run]) -> None:
    run = runs["moved"]
    assert run.code == 0
    assert run.counters["camera_cam_detector_markers_moved"] == 1
    m = re.search(rf"world marker {MOVED_ID} has moved: .*\(([-+.\d]+) ([-+.\d]+) ([-+.\d]+) m\)", run.log)
    assert m, run.log[-3000:]
    # The world file has it MOVE_M away from where it is: it is seen at minus that offset.
    np.testing.assert_allclose([float(v) for v in m.groups()], -np.array(MOVE_M), atol=0.01)
    texts = [t for t in run.statustexts if b"moved" in t]
    assert len(texts) == 1 and f"marker {MOVED_ID} moved".encode() in texts[0], run.statustexts
    # Only that marker.
    assert len(re.findall(r"marker \d+ has moved", run.log)) == 1
    # The node kept sending poses with the others.
    assert len(run.poses) >= 0.8 * len(runs["plain"].poses)
