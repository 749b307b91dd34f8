"""What the node keeps across restarts in ``state_dir``: the reset counter of its autopilot output.

A process that started its reset_counter at the value the autopilot last saw would not signal a
restart, and a pose jump across it would be fused as a normal measurement (PX4 and ArduPilot reset
their position to vision only when the counter changes). With a ``state_dir``, each start takes the
saved value plus one; without one, a value derived from the wall clock's seconds (it differs from
the last process's unless a multiple of 256 s passed with as many resets in between).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from atlas_onboard.fsio import write_atomic

_logger = logging.getLogger(__name__)


class ResetCounterStore:
    """The reset counter of ``entity``'s node, persisted in ``state_dir`` (None: not persisted)."""

    def __init__(self, state_dir: Path | None, entity: str) -> None:
        self.path = state_dir / f"reset-counter-{entity}.json" if state_dir is not None else None
        self.saved: int | None = None

    def initial(self, wall_ns: int) -> int:
        """The counter a new process starts with (saved at once): one past the last process's."""
        last = self._load()
        start = (last + 1) % 256 if last is not None else (wall_ns // 1_000_000_000) % 256
        self.save(start)
        return start

    def save(self, value: int) -> None:
        """Persist ``value`` if it changed (atomically: a crash leaves the old file or the new)."""
        if self.path is None or value == self.saved:
            return
        try:
            write_atomic(self.path, json.dumps({"reset_counter": int(value)}), make_dirs=True)
            self.saved = value
        except OSError as exc:
            self.saved = value  # said once per value, never raised: the pose still goes out
            _logger.warning("cannot save the reset counter to %s: %s", self.path, exc)

    def _load(self) -> int | None:
        if self.path is None:
            return None
        try:
            value = int(json.loads(self.path.read_text(encoding="utf-8"))["reset_counter"])
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            _logger.warning("unreadable reset counter in %s (%s): starting from the clock", self.path, exc)
            return None
        return value % 256
