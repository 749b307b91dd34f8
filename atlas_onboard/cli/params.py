"""``atlas-onboard params``: the autopilot's parameter file (:mod:`atlas_onboard.params`) for one entity."""

from __future__ import annotations

import argparse
from pathlib import Path

from atlas_onboard.config import load_node
from atlas_onboard.errors import AtlasError
from atlas_onboard.params import (
    ARDUPILOT_DEFAULT_VERSION,
    ARDUPILOT_VERSIONS,
    AUTOPILOTS,
    PX4_FRESH_SYSTEM_ID,
    parameters,
    render,
)


def _cmd_params(args: argparse.Namespace) -> int:
    from atlas_onboard.service.run import choose_entity

    world, node = load_node(args.config, choose_entity(args.config, args.entity))
    params = parameters(world, node, args.autopilot, args.delay_ms, args.cog_m, args.ardupilot_version)
    text = render(params, args.autopilot, node, world, args.vehicle_id, args.ardupilot_version)
    if args.out is None:
        print(text, end="")
        return 0
    try:
        Path(args.out).write_text(text, encoding="utf-8")
    except OSError as exc:
        raise AtlasError(f"--out: cannot write {args.out}: {exc.strerror}") from None
    print(f"wrote {args.out}: {len(params)} parameters for {args.autopilot}")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``params``."""
    p = sub.add_parser(
        "params",
        help="the autopilot's parameter file (QGroundControl / Mission Planner) for one entity",
        description="Write the PX4 (QGroundControl) or ArduPilot (Mission Planner) parameters for vision-only flight"
        " of ENTITY's drone, derived from the world file, each with a comment.",
    )
    p.add_argument("--autopilot", required=True, choices=AUTOPILOTS)
    p.add_argument("--config", required=True, type=Path, help="world file with a nodes section")
    p.add_argument("--entity", help="the drone's entity (default: the only one with node settings)")
    p.add_argument("--delay-ms", type=float, help="the measured vision delay, ms (default: the autopilot's default)")
    p.add_argument(
        "--cog-m", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
        help="the centre of gravity in the entity frame, world file's body axes, m (default: its origin)",
    )  # fmt: skip
    p.add_argument(
        "--vehicle-id", type=int, default=PX4_FRESH_SYSTEM_ID, metavar="ID",
        help="PX4: the flight controller's system id now, QGroundControl's Vehicle-Id column (default 1, a new one)",
    )  # fmt: skip
    p.add_argument(
        "--ardupilot-version", choices=ARDUPILOT_VERSIONS, default=ARDUPILOT_DEFAULT_VERSION,
        help=f"ArduPilot: the firmware's release, for its parameter names (default {ARDUPILOT_DEFAULT_VERSION})",
    )  # fmt: skip
    p.add_argument("--out", type=Path, help="write the file here (default: standard output)")
    p.set_defaults(func=_cmd_params)
