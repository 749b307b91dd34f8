"""The simulation a node process belongs to, read from the runner's ATLAS_SIM variable."""

import json
import threading

import pytest

from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.context import SIM_ENV, SimContext


def test_the_runner_s_variable_gives_the_scenario_seed_start_file_and_frames(monkeypatch, tmp_path):
    doc = {"scenario": "relay", "seed": 4, "epoch_file": str(tmp_path / "epoch"), "duration_s": 12.5,
           "frames_dir": str(tmp_path), "geometric": True, "replay": "realtime"}  # fmt: skip
    monkeypatch.setenv(SIM_ENV, json.dumps(doc))
    ctx = SimContext.from_env()
    assert ctx.scenario is scenarios.get("relay")
    assert (ctx.seed, ctx.epoch_file, ctx.duration_s) == (4, tmp_path / "epoch", 12.5)
    assert (ctx.frames_dir, ctx.geometric, ctx.replay) == (tmp_path, True, "realtime")


def test_defaults_where_the_runner_says_nothing(monkeypatch, tmp_path):
    monkeypatch.setenv(SIM_ENV, json.dumps({"scenario": "gaps", "epoch_file": "e", "duration_s": 3}))
    ctx = SimContext.from_env()
    assert (ctx.seed, ctx.frames_dir, ctx.geometric, ctx.replay) == (0, None, False, "")


@pytest.mark.parametrize("raw", ["", "not json", json.dumps({"scenario": "relay"}), json.dumps([1, 2])])
def test_a_missing_or_bad_variable_is_one_line_naming_it(monkeypatch, raw):
    monkeypatch.setenv(SIM_ENV, raw)
    with pytest.raises(AtlasError, match=SIM_ENV) as info:
        SimContext.from_env()
    assert "\n" not in str(info.value)


def test_the_start_time_is_read_from_the_runner_s_file_or_none_once_stopped(tmp_path):
    ctx = SimContext(scenarios.get("relay"), 0, tmp_path / "epoch", 1.0)
    stop = threading.Event()
    stop.set()
    assert ctx.wait_epoch(stop) is None  # stopped before the runner wrote it
    (tmp_path / "epoch").write_text("1700000000.25", encoding="utf-8")
    assert ctx.wait_epoch(threading.Event()) == 1700000000.25
