"""How many processor cores a node's detection may use (``nodes.<entity>.cores``), and how its cameras
share them."""

from __future__ import annotations

import os
from collections.abc import Callable

RESERVED_CORES = 1
"""Left to the autopilot link, the node's own loop and the system when the setting is 0 (automatic)."""


def node_cores(setting: int, affinity: Callable[[int], set[int]] = os.sched_getaffinity) -> int:
    """The cores the node uses: ``setting`` (at most the cores the process may run on), or for 0 the
    cores the process may run on (its CPU affinity, which ``taskset`` and systemd's ``CPUAffinity``
    set) less ``RESERVED_CORES``; at least 1."""
    allowed = len(affinity(0))
    if setting == 0:
        return max(allowed - RESERVED_CORES, 1)
    return max(min(setting, allowed), 1)


def processes_per_camera(cores: int, cameras: int) -> int:
    """Detection worker processes for each of ``cameras`` cameras given ``cores`` cores: 0 with one core
    (each camera detects in its own thread, the serial path), else the camera's share of the cores, at
    least one (a camera of its own process, whatever the other cameras do)."""
    if cores <= 1 or cameras <= 0:
        return 0
    return max(cores // cameras, 1)
