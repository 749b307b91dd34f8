"""The simulator's UDP hub on loopback: every datagram reaches every other known client and never its
sender, the tap sees each one, a drop rate drops (counted), and the client list is bounded."""

from __future__ import annotations

import socket

import pytest

from atlas_onboard.sim.hub import Hub


def _client() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(5.0)
    return s


def _recv(s: socket.socket) -> bytes:
    return s.recvfrom(65535)[0]


def _quiet(s: socket.socket) -> bool:
    s.settimeout(0.2)
    try:
        s.recvfrom(65535)
    except TimeoutError:
        return True
    finally:
        s.settimeout(5.0)
    return False


@pytest.fixture
def clients():
    socks = [_client() for _ in range(3)]
    yield socks
    for s in socks:
        s.close()


def test_a_datagram_reaches_every_other_known_client_and_the_tap(clients):
    tapped: list[tuple[bytes, tuple[str, int]]] = []
    hub = Hub(tap=lambda data, addr, _t: tapped.append((data, addr))).start()
    try:
        a, b, c = clients
        a.sendto(b"hello-a", ("127.0.0.1", hub.port))
        b.sendto(b"hello-b", ("127.0.0.1", hub.port))
        assert _recv(a) == b"hello-b"  # a was known when b spoke
        c.sendto(b"hello-c", ("127.0.0.1", hub.port))
        assert _recv(a) == b"hello-c" and _recv(b) == b"hello-c"
        a.sendto(b"to-all", ("127.0.0.1", hub.port))
        assert _recv(b) == b"to-all" and _recv(c) == b"to-all"
        assert _quiet(a)  # never echoed to its sender
        assert hub.clients == [s.getsockname() for s in clients]
        assert [d for d, _ in tapped] == [b"hello-a", b"hello-b", b"hello-c", b"to-all"]
        assert [addr for _, addr in tapped] == [s.getsockname() for s in (a, b, c, a)]
        assert hub.forwarded == 0 + 1 + 2 + 2 and hub.dropped == 0
    finally:
        hub.stop()


def test_a_drop_rate_of_one_forwards_nothing_and_counts_every_drop(clients):
    hub = Hub(drop_rate=1.0).start()
    try:
        a, b, _ = clients
        b.sendto(b"first", ("127.0.0.1", hub.port))
        for k in range(5):
            a.sendto(b"lost %d" % k, ("127.0.0.1", hub.port))
        assert _quiet(b)
        assert hub.dropped == 6 and hub.forwarded == 0
    finally:
        hub.stop()


def test_clients_beyond_the_bound_are_not_learned(clients):
    hub = Hub(max_clients=2).start()
    try:
        a, b, c = clients
        a.sendto(b"a", ("127.0.0.1", hub.port))
        b.sendto(b"b", ("127.0.0.1", hub.port))
        assert _recv(a) == b"b"
        c.sendto(b"c", ("127.0.0.1", hub.port))  # forwarded, but c is not learned
        assert _recv(a) == b"c" and _recv(b) == b"c"
        a.sendto(b"again", ("127.0.0.1", hub.port))
        assert _recv(b) == b"again" and _quiet(c)
        assert hub.clients == [a.getsockname(), b.getsockname()]
    finally:
        hub.stop()
