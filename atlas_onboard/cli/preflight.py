"""``atlas-onboard preflight``: the bench check before the first flight (:mod:`atlas_onboard.preflight.bench`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from atlas_onboard.preflight.bench import run_preflight


def _cmd_preflight(args: argparse.Namespace) -> int:
    from atlas_onboard.service.run import choose_entity

    entity = choose_entity(args.config, args.entity)
    return run_preflight(args.config, entity, args.seconds, print, input if args.interactive else None)


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``preflight``."""
    p = sub.add_parser(
        "preflight",
        help="bench check before the first flight: attitude, frames, delay, rate, TIMESYNC, origin, signing",
        description="Run the node (its service stopped) with the drone still on the bench, propellers off, relay"
        " its autopilot link, and check what the autopilot gets: one line per check, PASS, FAIL (with the fix)"
        " or SKIP. Exit status 0 only when nothing failed.",
    )
    p.add_argument("--config", required=True, type=Path, help="world file with a nodes section")
    p.add_argument("--entity", help="the drone's entity (default: the only one with node settings)")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to watch after the first pose (default 10)")
    p.add_argument("--interactive", action="store_true", help="then ask for a tilt nose down and right, check signs")
    p.set_defaults(func=_cmd_preflight)
