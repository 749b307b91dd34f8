"""The nodes section's reader: defaults merged with each node's own section, and bad node settings."""

import pytest

from tests.config.common import NODES, cli


def test_node_settings_merge_defaults_and_entity(tmp_path):
    from atlas_onboard.config import AutopilotOutput, load_node

    f = tmp_path / "w.yaml"
    f.write_text(NODES)
    _, n1 = load_node(f, "drone1")
    assert n1.system_id == 11 and n1.fused_rate_hz == 5.0
    assert n1.autopilot.link.url == "udpout:127.0.0.1:14540"  # from defaults
    assert n1.autopilot.output is AutopilotOutput.ODOMETRY and n1.autopilot.rate_hz == 20  # merged
    assert [p.url for p in n1.peers] == ["udpin:0.0.0.0:14600", "udpout:127.0.0.1:14601"]
    assert [p.tunnel for p in n1.peers] == [False, True]
    _, n2 = load_node(f, "drone2")
    assert n2.autopilot.output is AutopilotOutput.VISION_POSITION_ESTIMATE and n2.fused_rate_hz == 2.0


LANDING = (
    NODES + "    landing: {target: drone1, autopilot: ardupilot, marker: 10, point_m: [0, 0.05, 0], max_age_s: 0.2}\n"
)


def test_landing_section(tmp_path):
    from atlas_onboard.config import load_node

    f = tmp_path / "w.yaml"
    f.write_text(LANDING)
    _, n2 = load_node(f, "drone2")
    ld = n2.landing
    assert (ld.target, ld.autopilot, ld.marker, ld.point_m) == ("drone1", "ardupilot", 10, (0.0, 0.05, 0.0))
    assert (ld.rate_hz, ld.max_age_s, ld.max_sigma_m) == (20.0, 0.2, 0.05)  # declared defaults, one set
    assert load_node(f, "drone1")[1].landing is None


BAD_NODES = [
    (
        "unknown node key",
        NODES.replace("fused_rate_hz: 2", "fused_rate_hz: 2\n    autopilt: {}"),
        "nodes.drone2.autopilt",
        "did you mean 'autopilot'",
    ),
    (
        "bad url",
        NODES.replace("udpout:127.0.0.1:14540", "udp://127.0.0.1:14540"),
        "nodes.defaults.autopilot.url",
        "connection string",
    ),
    (
        "bad peer url",
        NODES.replace('"udpin:0.0.0.0:14600"', '"udpin:0.0.0.0"'),
        "nodes.defaults.peers[0].url",
        "connection string",
    ),
    ("missing system id", NODES.replace("    system_id: 12\n", ""), "nodes.drone2.system_id", "missing required field"),
    (
        "duplicate system id",
        NODES.replace("system_id: 12", "system_id: 11"),
        "nodes.drone2.system_id",
        "duplicate system id 11",
    ),
    ("unknown entity", NODES + "  drone9: {system_id: 3}\n", "nodes.drone9", "unknown key"),
    (
        "bad output",
        NODES.replace("output: odometry", "output: odom"),
        "nodes.drone1.autopilot.output",
        "vision_position_estimate",
    ),
    ("bad rate", NODES.replace("rate_hz: 20", "rate_hz: 0"), "nodes.defaults.autopilot.rate_hz", "rate in [1, 200] Hz"),
    (
        "landing on no entity",
        LANDING.replace("target: drone1", "target: rover"),
        "nodes.drone2.landing.target",
        "unknown entity 'rover'",
    ),
    (
        "landing on another's marker",
        LANDING.replace("marker: 10", "marker: 0"),
        "nodes.drone2.landing.marker",
        "0 is not a marker of drone1",
    ),
    (
        "landing for no autopilot",
        LANDING.replace("autopilot: ardupilot", "autopilot: apm"),
        "nodes.drone2.landing.autopilot",
        "px4, ardupilot",
    ),
    (
        "landing too slow",
        LANDING.replace("max_age_s: 0.2", "rate_hz: 1"),
        "nodes.drone2.landing.rate_hz",
        "rate in [2, 50] Hz",
    ),
    ("landing point", LANDING.replace("[0, 0.05, 0]", "[0, 0.05]"), "nodes.drone2.landing.point_m", "3"),
    (
        "tunnel not bool",
        NODES.replace("tunnel: true", "tunnel: yes please"),
        "nodes.defaults.peers[1].tunnel",
        "true or false",
    ),
]


@pytest.mark.parametrize(("what", "text", "path", "words"), BAD_NODES, ids=[b[0] for b in BAD_NODES])
def test_bad_node_settings_name_the_field(capsys, tmp_path, what, text, path, words):
    f = tmp_path / "world.yaml"
    f.write_text(text)
    code, _, err = cli(capsys, "check-config", str(f))
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert f"{path}: " in err and words in err, err
