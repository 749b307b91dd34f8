"""The records the node and its transport exchange."""

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.records import Inbound


def _md(sensor_id, marker_id, capture_time_us, origin=0):
    return MarkerData(sensor_id, marker_id, 0.01, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0), capture_time_us, origin=origin)


def test_an_inbound_is_decoded_once_and_a_refused_one_stays_refused():
    calls = []
    item = Inbound(2, 1, 0, 5, 0, 0, lambda: calls.append(1))  # the transport refused it (returns None)
    assert item.take() is None and item.take() is None and calls == [1]
    ready = Inbound.of(_md(1, 0, 5), 7)
    assert ready.take() == _md(1, 0, 5) and ready.arrival_ns == 7 and ready.edge == (1, 0)


def test_an_inbound_says_its_edge_and_image_from_the_frame_alone():
    decoded = []
    item = Inbound(9, 3, 41, 1_000_250, 2, 17, lambda: decoded.append(1) or _md(3, 41, 1_000_250, origin=9))
    assert item.edge == (3, 41) and item.image == (9, 3, 1_000_250) and item.frame_remaining == 2
    assert decoded == []  # nothing decoded to say so
    assert item.take() == _md(3, 41, 1_000_250, origin=9) and decoded == [1]
