"""The node's scheduling pieces (atlas_onboard/node/schedule.py): relevance, the parking buffer, the inbox,
the frame count. Pure: no node, no clock."""

import threading

import pytest
from hypothesis import given
from hypothesis import strategies as st

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.records import Inbound
from atlas_onboard.node.schedule import Changes, Inbox, ParkingBuffer, Relevance, near_entities, relevance

# --- relevance ------------------------------------------------------------------------------------


def test_near_entities_are_the_own_and_those_nearer_the_world():
    levels = {"world": 0, "ceiling": 1, "d1": 2, "d2": 2, "d3": 3}
    assert near_entities("d1", levels) == {"ceiling", "d1"}
    assert near_entities("d3", levels) == {"ceiling", "d1", "d2", "d3"}
    assert near_entities("ceiling", levels) == {"ceiling"}
    assert near_entities("world", levels) == frozenset()  # the world's pose never changes
    assert near_entities("d4", levels) is None  # no pose yet: every observation can move it
    assert near_entities("d1", None) is None  # Dijkstra's paths: no levels


def test_relevance_of_an_edge():
    near = near_entities("d1", {"world": 0, "lead": 1, "d1": 2, "d2": 2})
    assert relevance("world", "d2", near) is Relevance.PARK  # a ceiling camera's view of another drone
    assert relevance("d2", "world", near) is Relevance.PARK
    assert relevance("world", "d1", near) is Relevance.NOW  # of the own entity
    assert relevance("d1", "d2", near) is Relevance.NOW  # by the own entity
    assert relevance("d2", "lead", near) is Relevance.NOW  # of an entity the own pose rests on
    assert relevance("lead", "d2", near) is Relevance.NOW  # by one
    assert relevance(None, "d2", near) is Relevance.NOW  # an unknown id: the listener refuses and counts it
    assert relevance("world", None, near) is Relevance.NOW
    assert relevance("world", "d2", None) is Relevance.NOW  # no own pose yet


@given(
    levels=st.dictionaries(st.sampled_from("abcdefgh"), st.integers(0, 6), max_size=8),
    own=st.sampled_from("abcdefgh"),
    observer=st.sampled_from("abcdefgh"),
    observed=st.sampled_from("abcdefgh"),
)
def test_only_edges_away_from_the_own_pose_are_parked(levels, own, observer, observed):
    """PARK exactly when the own entity has a level and neither end is the own entity or an entity
    nearer the world than it (level >= 1)."""
    got = relevance(observer, observed, near_entities(own, levels))
    level = levels.get(own)
    if level is None:
        assert got is Relevance.NOW
        return

    def near(e):
        return e == own or 1 <= levels.get(e, -1) < level

    assert (got is Relevance.PARK) == (not near(observer) and not near(observed))


# --- the parking buffer ---------------------------------------------------------------------------


def md(sensor_id, marker_id, capture_time_us):
    return MarkerData(sensor_id, marker_id, 0.01, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0), capture_time_us)


def arrival(sensor_id, marker_id, capture_time_us, arrival_ns, decoded=None):
    """An observation as delivered undecoded; ``decoded`` records the edges taken."""
    record = md(sensor_id, marker_id, capture_time_us)

    def admit():
        if decoded is not None:
            decoded.append((sensor_id, marker_id, capture_time_us))
        return record

    return Inbound(2, sensor_id, marker_id, capture_time_us, 0, arrival_ns, admit)


observations = st.lists(
    st.tuples(st.integers(1, 3), st.integers(0, 3), st.integers(0, 50)), min_size=0, max_size=40
)  # (sensor, marker, capture time): edges and times repeat


@given(observations)
def test_newest_of_each_edge_wins_whatever_the_arrival_order(obs):
    """With newest_wins, what is taken is, per edge, the observation with the latest capture time
    (the first to arrive of equal ones), whatever order they came in; every other arrival is
    counted once as superseded; only the taken are decoded."""
    buffer = ParkingBuffer(capacity=1000, newest_wins=True)
    decoded = []
    buffer.put(arrival(s, m, t, arrival_ns=k, decoded=decoded) for k, (s, m, t) in enumerate(obs))
    taken = [(item.take(), item.arrival_ns) for item in buffer.take()]
    expected = {}
    for k, (s, m, t) in enumerate(obs):
        if (s, m) not in expected or t > expected[(s, m)][0]:
            expected[(s, m)] = (t, k)
    assert {(r.sensor_id, r.marker_id): (r.capture_time_us, a) for r, a in taken} == expected
    assert [a for _, a in taken] == sorted(a for _, a in taken)  # in order of arrival
    assert buffer.superseded == len(obs) - len(expected) and buffer.dropped == 0
    assert sorted(decoded) == sorted((s, m, t) for (s, m), (t, _) in expected.items())
    assert len(buffer) == 0 and buffer.since_ns() is None


@given(observations)
def test_without_newest_wins_every_observation_is_kept_in_arrival_order(obs):
    buffer = ParkingBuffer(capacity=1000, newest_wins=False)
    buffer.put(arrival(s, m, t, arrival_ns=k) for k, (s, m, t) in enumerate(obs))
    taken = [item.take() for item in buffer.take()]
    assert [(r.sensor_id, r.marker_id, r.capture_time_us) for r in taken] == obs
    assert buffer.superseded == 0 and buffer.dropped == 0


@given(observations, st.integers(1, 8), st.booleans())
def test_the_buffer_is_bounded_and_drops_the_oldest(obs, capacity, newest_wins):
    """Never more than ``capacity`` parked; what goes is the oldest arrival, each counted once:
    every arrival is taken, superseded or dropped."""
    buffer = ParkingBuffer(capacity=capacity, newest_wins=newest_wins)
    for k, (s, m, t) in enumerate(obs):
        buffer.put([arrival(s, m, t, arrival_ns=k)])
        assert len(buffer) <= capacity
    taken = buffer.take()
    assert len(taken) + buffer.superseded + buffer.dropped == len(obs)
    if not newest_wins:  # the last ``capacity`` arrivals
        assert [item.arrival_ns for item in taken] == list(range(len(obs)))[-capacity:]


def test_since_is_the_first_arrival_of_a_park_period():
    buffer = ParkingBuffer(capacity=4, newest_wins=True)
    assert buffer.since_ns() is None
    buffer.put([arrival(1, 0, 10, arrival_ns=500), arrival(1, 0, 11, arrival_ns=700)])
    assert buffer.since_ns() == 500  # the first stays the period's start though superseded
    buffer.take()
    buffer.put([arrival(1, 0, 12, arrival_ns=900)])
    assert buffer.since_ns() == 900
    with pytest.raises(ValueError, match="capacity"):
        ParkingBuffer(capacity=0, newest_wins=True)


# --- the inbox and the frame count ---------------------------------------------------------------------


def test_inbox_drops_oldest_when_full():
    box = Inbox(3)
    items = [(MarkerData(1, 0, 0.01, (0, 0, 1), (1, 0, 0, 0), k), k, True) for k in range(5)]
    for it in items:
        box.put(it)
    assert box.dropped == 2
    assert [box.get(0)[1] for _ in range(3)] == [2, 3, 4]
    assert box.get(0) is None


def test_inbox_items_that_need_no_wake_wait_until_it_is_half_full():
    box = Inbox(8)
    got = []
    consumer = threading.Thread(target=lambda: got.append(box.get(timeout_s=60)))
    consumer.start()
    items = [(MarkerData(1, 0, 0.01, (0, 0, 1), (1, 0, 0, 0), k), k, False) for k in range(4)]
    box.put_many(items[:3], wake=False)
    consumer.join(0.3)
    assert consumer.is_alive() and not got  # three of eight: left for the consumer's next tick
    box.put_many(items[3:], wake=False)  # half full: woken, so that none is lost
    consumer.join(10)
    assert not consumer.is_alive() and got[0][1] == 0
    assert [box.get(0)[1] for _ in range(3)] == [1, 2, 3] and box.dropped == 0


# --- when the graph is evaluated ---------------------------------------------------------------------


def test_changes_say_when_the_graph_is_evaluated():
    ms = 1_000_000
    changes = Changes(coalesce_ns=50 * ms)
    assert not changes.due(0) and changes.due_ns(0) is None  # nothing accepted
    changes.pending = changes.others = True  # a view of another drone, at 10 ms
    assert not changes.due(10 * ms) and changes.due_ns(10 * ms) == 50 * ms and changes.due(50 * ms)
    changes.urgent = True  # then one of the own entity: at once
    assert changes.due(20 * ms) and changes.due_ns(20 * ms) == 20 * ms
    changes.evaluated(20 * ms, complete=False, rest_unchanged=True)  # the own pose alone
    assert not changes.urgent and changes.due_ns(20 * ms) == 50 * ms  # the others' view still waits
    changes.evaluated(50 * ms, complete=True)
    assert changes.due_ns(60 * ms) is None and changes.last_full_ns == 50 * ms
    changes.pending = changes.urgent = True  # only the own entity's edge to the world changed
    changes.evaluated(70 * ms, complete=False, rest_unchanged=True)
    assert changes.due_ns(70 * ms) is None  # a full evaluation would change nothing
    changes.pending = changes.urgent = True
    changes.evaluated(80 * ms, complete=False, rest_unchanged=False)  # an entity rests on the own pose
    assert changes.due_ns(80 * ms) == 100 * ms


def test_clearing_the_buffer_keeps_its_counts_and_may_switch_its_mode():
    """A reload drops what is parked and may change whether only the newest of an edge counts; the
    counters of superseded and dropped observations go on (they never decrease)."""
    buffer = ParkingBuffer(capacity=1, newest_wins=True)
    buffer.put([arrival(1, 0, 10, 0), arrival(1, 0, 11, 1), arrival(2, 0, 10, 2)])
    assert (buffer.superseded, buffer.dropped, len(buffer)) == (1, 1, 1)
    buffer.clear(newest_wins=False)
    assert (buffer.superseded, buffer.dropped, len(buffer), buffer.since_ns()) == (1, 1, 0, None)
    buffer.put([arrival(1, 0, 12, 3)])
    buffer.put([arrival(1, 0, 13, 4)])  # every one counts now: the older is dropped for room, not superseded
    assert (buffer.superseded, buffer.dropped) == (1, 2) and buffer.take()[0].capture_time_us == 13


def test_parked_observations_of_an_image_count_as_seen():
    """An image of four observations, two parked (one of them its last): the two queued complete it."""
    from atlas_onboard.node.schedule import FrameCount

    obs = [md(10, m, 500) for m in (5, 7, 6, 8)]
    obs = [MarkerData(o.sensor_id, o.marker_id, o.sigma_m, o.p_sensor_marker_m, o.q_sensor_marker_wxyz,
                      o.capture_time_us, origin=3, frame_remaining=3 - i) for i, o in enumerate(obs)]  # fmt: skip
    buffer = ParkingBuffer(capacity=8, newest_wins=True)
    buffer.put([Inbound.of(o, 0) for o in obs[2:]])  # 6 and 8: parked
    assert buffer.parked_of((3, 10, 500)) == (2, 1) and buffer.parked_of((4, 10, 500)) is None
    queued = [(o, 0, False) for o in obs[:2]]
    alone = FrameCount()
    alone.add(queued)
    assert alone.incomplete == 1  # without the tally: two of four seen
    frames = FrameCount(parked=buffer.parked_of)
    frames.add(queued)
    assert frames.incomplete == 0
    buffer.take()
    assert buffer.parked_of((3, 10, 500)) is None  # a tally lasts one park period
