"""A UDP hub on 127.0.0.1 that forwards every datagram to every other client: the swarm's WiFi mesh
(or a mavlink-router) in one process. Each node's peer link is ``udpout:127.0.0.1:<hub port>``; the
hub learns a client's address from its first datagram (every node sends a HEARTBEAT at start).

The hub can also hand each datagram to a tap (the simulator uses one to read fused poses and count
observations), and it can drop datagrams at a given rate to test what a lossy link does.
"""

from __future__ import annotations

import random
import socket
import threading
import time
from collections.abc import Callable

Tap = Callable[[bytes, tuple[str, int], float], None]


class Hub:
    """Forward datagrams between all known clients (bounded: at most ``max_clients`` addresses)."""

    def __init__(self, tap: Tap | None = None, drop_rate: float = 0.0, seed: int = 0, max_clients: int = 64) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.05)
        self.port: int = self._sock.getsockname()[1]
        self.clients: list[tuple[str, int]] = []
        self.forwarded = 0
        self.dropped = 0
        self._tap = tap
        self._drop_rate = drop_rate
        self._rng = random.Random(seed)
        self._max = max_clients
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-hub", daemon=True)

    def start(self) -> Hub:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self._sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            if addr not in self.clients and len(self.clients) < self._max:
                self.clients.append(addr)
            if self._tap is not None:
                self._tap(data, addr, time.time())
            if self._drop_rate and self._rng.random() < self._drop_rate:
                self.dropped += 1
                continue
            for client in self.clients:
                if client != addr:
                    try:
                        self._sock.sendto(data, client)
                        self.forwarded += 1
                    except OSError:
                        pass
