"""Named event counters, the one counters type of the node's blocks (listener, gate, links, transport)."""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator

from atlas_onboard.core.rejection import Rejection


class Counters:
    """Named event counters, safe to increment from one thread while another reads them. A
    :class:`Rejection` is counted under its counter name (``rejected_<value>``)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, int] = {}

    def inc(self, name: str | Rejection, n: int = 1) -> None:
        key = name.counter if isinstance(name, Rejection) else name
        with self._lock:
            self._values[key] = self._values.get(key, 0) + n

    def update(self, names: Iterable[str | Rejection]) -> None:
        """Count each of ``names`` once."""
        for name in names:
            self.inc(name)

    def __getitem__(self, name: str | Rejection) -> int:
        return self._values.get(name.counter if isinstance(name, Rejection) else name, 0)

    def get(self, name: str | Rejection, default: int = 0) -> int:
        return self._values.get(name.counter if isinstance(name, Rejection) else name, default)

    def values(self) -> list[int]:
        return list(self.snapshot().values())

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._values)

    def items(self) -> Iterator[tuple[str, int]]:
        return iter(self.snapshot().items())

    def __repr__(self) -> str:
        return f"Counters({self.snapshot()})"
