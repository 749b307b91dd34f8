"""A node of a simulated run: ``python -m atlas_onboard.sim.launch ARGS`` is ``atlas-onboard ARGS`` with
the simulator plugged in.

The runner starts each node with this: it ties the node's life to the runner's, registers the ``sim``
camera source (the scenario's cameras and motion capture, :func:`atlas_onboard.sim.sources.sim_camera`)
and runs the ordinary command line, so production start-up knows nothing of the simulator. The
simulated autopilot needs nothing here: it is a MAVLink peer on the node's autopilot link.
"""

from __future__ import annotations

import contextlib
import ctypes
import signal
import sys
from collections.abc import Sequence

from atlas_onboard import cli
from atlas_onboard.service.run import register_camera_kind
from atlas_onboard.sim.scenario import SIM_KIND
from atlas_onboard.sim.sources import sim_camera


def die_with_parent() -> None:
    """SIGTERM to this process when the runner dies, even on a crash.

    (Set by the child itself rather than in ``preexec_fn``, which is unsafe while threads run.)
    """
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``atlas-onboard`` with ``argv`` in a node of a simulated run."""
    die_with_parent()
    register_camera_kind(SIM_KIND, sim_camera)
    return cli.main(argv)


if __name__ == "__main__":
    sys.exit(main())
