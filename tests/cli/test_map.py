"""The map command on rendered frames of the simulator's map scenario: record then map round trip, and
one-line refusals for empty, unreadable or frameless recordings, no anchor seen and missing inputs; groups
never seen together mapped each from its own anchor."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from atlas_onboard.cli import main
from atlas_onboard.config import load_world
from tests.mapping.rendered import MAP_WORLD, render_frames, write_folder


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[np.ndarray]]:
    """Four seconds of the mapper's camera, every other frame (7.5 fps) as an image folder, and its calibration."""
    tmp = tmp_path_factory.mktemp("flight")
    images, intr = render_frames(list(range(600, 660, 2)))
    folder, cal = write_folder(tmp, images, intr)
    return folder, cal, images


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_record_then_map_round_trip(tmp_path: Path, flight, capsys: pytest.CaptureFixture[str]) -> None:
    folder, cal, images = flight
    rec = tmp_path / "rec"
    code, out, err = _run(["record", "--config", str(MAP_WORLD), "--sensor", "cam", "--source", str(folder),
                           "--calibration", str(cal), "--out", str(rec)], capsys)  # fmt: skip
    assert code == 0, err
    assert f"wrote {len(images)} frames" in out
    index = [json.loads(line) for line in (rec / "index.jsonl").read_text().splitlines()]
    assert len(index) == len(images) and any(r["markers"] for r in index)
    out_world = tmp_path / "mapped.yaml"
    code, out, err = _run(["map", str(rec), "--config", str(MAP_WORLD), "--anchor", "4", "--out", str(out_world),
                           "--report", str(tmp_path / "report"), "--no-plot"], capsys)  # fmt: skip
    assert code == 0, err
    truth = load_world(MAP_WORLD).markers
    mapped = load_world(out_world).markers
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    statuses = {m["id"]: m["status"] for m in report["markers"]}
    assert statuses[4] == "anchor"
    # Markers seen only from one direction are named "degenerate" (their tilt may be the mirror
    # image, which no first-order sigma describes); the others must be as good as their sigma says.
    good = [m for m, s in statuses.items() if s in ("mapped", "degenerate")]
    assert len(good) >= 4
    for m in good:
        err_m = np.linalg.norm(mapped[m].T_entity_marker.translation - truth[m].T_entity_marker.translation)
        ang = (mapped[m].T_entity_marker.rotation * truth[m].T_entity_marker.rotation.inv()).magnitude()
        rec_m = next(x for x in report["markers"] if x["id"] == m)
        # Each error within what the map reports (4 sigma of the 3-D error, a millimetre for the rendering).
        assert err_m < 4 * np.linalg.norm(rec_m["sigma_m"]) + 0.001, (m, err_m, rec_m)
        if rec_m["status"] == "mapped":
            assert np.degrees(ang) < 4 * np.linalg.norm(rec_m["sigma_deg"]) + 0.1, (m, np.degrees(ang), rec_m)
    assert np.allclose(mapped[4].T_entity_marker.as_matrix(), truth[4].T_entity_marker.as_matrix())


def _assert_refused(code: int, out: str, err: str, tmp: Path, *needles: str) -> None:
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("atlas-onboard: error:"), err
    for n in needles:
        assert n in lines[0], lines[0]
    assert not (tmp / "out.yaml").exists() and not (tmp / "report").exists()
    assert not [p for p in tmp.iterdir() if p.name.startswith(".out.yaml")]


def _map_args(tmp: Path, *inputs: Path, anchor: str = "4", extra: tuple[str, ...] = ()) -> list[str]:
    return ["map", *map(str, inputs), "--config", str(MAP_WORLD), "--anchor", anchor, "--out", str(tmp / "out.yaml"),
            "--report", str(tmp / "report"), *extra]  # fmt: skip


def test_empty_recording_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    _assert_refused(*_run(_map_args(tmp_path, tmp_path / "empty"), capsys), tmp_path, "empty")


def test_unreadable_recording_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "recording.json").write_text("{not json")
    _assert_refused(*_run(_map_args(tmp_path, rec), capsys), tmp_path, "recording.json")


def test_recording_without_frames_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from atlas_onboard.detector.calibration import Calibration
    from atlas_onboard.recording.format import RecordingWriter

    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    RecordingWriter(tmp_path / "rec", Calibration(640, 480, K, np.zeros(5))).close()
    _assert_refused(*_run(_map_args(tmp_path, tmp_path / "rec"), capsys), tmp_path, "no frames")


def test_no_anchor_seen_exits_2(tmp_path: Path, flight, capsys: pytest.CaptureFixture[str]) -> None:
    folder, cal, _ = flight
    args = _map_args(tmp_path, folder, anchor="11", extra=("--calibration", str(cal)))
    _assert_refused(*_run(args, capsys), tmp_path, "no anchor seen", "11")


def test_map_needs_an_anchor_and_existing_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _assert_refused(*_run(_map_args(tmp_path, tmp_path / "nothing"), capsys), tmp_path, "no such file")


def _two_groups() -> tuple[tuple[frozenset[int], list[int]], tuple[frozenset[int], list[int]]]:
    """Two sets of frames of the map scenario's flight whose markers are never seen together."""
    from atlas_onboard.sim import scenarios
    from atlas_onboard.sim.world import SimWorld

    sim = SimWorld(scenarios.get("map"))
    seen = {j: frozenset(s.marker.id for s in sim.sightings(1, sim.truth(j / 15), j / 15)) for j in range(0, 900, 3)}
    groups: list[tuple[frozenset[int], list[int]]] = []
    for j, ids in seen.items():
        if len(ids) < 2:
            continue
        for g, frames in groups:
            if ids == g:
                frames.append(j)
                break
        else:
            groups.append((ids, [j]))
    pairs = [(a, b) for a in groups for b in groups if len(a[1]) >= 5 and len(b[1]) >= 5 and not (a[0] & b[0])]
    return pairs[0]


def test_groups_never_seen_together_are_each_mapped_from_their_own_anchor(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A flight that never shows both groups in one image (a hangar): with an anchor in each group,
    both are mapped; with an anchor in one only, that one is mapped and the other reported."""
    (ga, fa), (gb, fb) = _two_groups()
    images, intr = render_frames(fa[:5] + fb[:5])
    folder, cal = write_folder(tmp_path, images, intr)
    truth = {m.id: m.T_entity_marker.translation for m in load_world(MAP_WORLD).markers.values()}
    # Frames 0.2 s apart from two moments of the flight: searched whole (no tracking between them).
    sparse = ("--calibration", str(cal), "--min-frames", "3", "--decimate", "1")
    both = _map_args(tmp_path, folder, anchor=str(min(ga)), extra=(*sparse, "--anchor", str(min(gb))))
    code, out, err = _run(both, capsys)
    assert code == 0, err
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    status = {r["id"]: r["status"] for r in report["markers"]}
    assert {status[m] for m in ga | gb} <= {"anchor", "mapped", "degenerate"}, status
    mapped = {m.id: m.T_entity_marker.translation for m in load_world(tmp_path / "out.yaml").markers.values()}
    for m in (ga | gb) - {min(ga), min(gb)}:
        assert np.linalg.norm(mapped[m] - truth[m]) < 0.05, (m, mapped[m], truth[m])

    one = tmp_path / "one"
    one.mkdir()
    code, out, err = _run(_map_args(one, folder, anchor=str(min(ga)), extra=sparse), capsys)
    assert code == 0, err
    status = {r["id"]: r["status"] for r in json.loads((one / "report" / "report.json").read_text())["markers"]}
    assert {status[m] for m in gb} == {"unanchored"} and {status[m] for m in ga} <= {"anchor", "mapped", "degenerate"}
    assert ", ".join(map(str, sorted(gb))) in out and "no anchor" in out
