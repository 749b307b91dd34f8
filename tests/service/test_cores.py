"""The cores a node's detection may use: the setting, its default from the CPU affinity, the share of
each camera."""

import pytest

from atlas_onboard.config import load_node
from atlas_onboard.errors import ConfigError
from atlas_onboard.service.cores import RESERVED_CORES, node_cores, processes_per_camera
from tests.config.common import NODES


def _affinity(n: int):
    return lambda pid: set(range(n))


@pytest.mark.parametrize("allowed", [1, 2, 3, 4, 8, 64])
def test_default_is_the_affinity_less_one_at_least_one(allowed):
    assert node_cores(0, _affinity(allowed)) == max(allowed - RESERVED_CORES, 1)
    assert RESERVED_CORES == 1


def test_default_on_a_pi4_and_under_taskset():
    assert node_cores(0, _affinity(4)) == 3  # a Pi 4: one core left to the autopilot link and the system
    assert node_cores(0, lambda pid: {0, 1}) == 1  # taskset -c 0,1: the serial path
    assert node_cores(0, lambda pid: {2, 5, 7}) == 2  # the count of allowed cores, not their numbers


@pytest.mark.parametrize(("setting", "allowed", "expected"), [(1, 4, 1), (2, 4, 2), (4, 4, 4), (8, 2, 2), (3, 1, 1)])
def test_a_setting_is_taken_up_to_the_cores_allowed(setting, allowed, expected):
    assert node_cores(setting, _affinity(allowed)) == expected


@pytest.mark.parametrize(
    ("cores", "cameras", "expected"),
    [(1, 1, 0), (1, 3, 0), (2, 1, 2), (3, 1, 3), (3, 2, 1), (3, 3, 1), (2, 3, 1), (6, 3, 2)],
)
def test_processes_per_camera(cores, cameras, expected):
    assert processes_per_camera(cores, cameras) == expected


def _node(tmp_path, extra: str):
    f = tmp_path / "w.yaml"
    f.write_text(NODES.replace("    fused_rate_hz: 2\n", f"    fused_rate_hz: 2\n{extra}"))
    return load_node(f, "drone2")[1]


def test_the_setting_is_read_with_default_zero(tmp_path):
    assert _node(tmp_path, "").cores == 0
    assert _node(tmp_path, "    cores: 3\n").cores == 3


@pytest.mark.parametrize(
    ("value", "message"),
    [("-1", "expected an integer in [0, 1024]"), ("two", "expected an integer"), ("1.5", "expected an integer")],
)
def test_bad_cores_are_one_line_errors(tmp_path, value, message):
    with pytest.raises(ConfigError) as err:
        _node(tmp_path, f"    cores: {value}\n")
    assert "nodes.drone2.cores" in str(err.value) and message in str(err.value)
