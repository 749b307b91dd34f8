"""The ``atlas-onboard`` command: a thin layer over ordinary functions.

Known errors (:class:`~atlas_onboard.errors.AtlasError`) become one line on stderr and exit status 2;
only the unexpected keeps its traceback.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

from atlas_onboard import __version__
from atlas_onboard.errors import AtlasError

if TYPE_CHECKING:
    from atlas_onboard.config import WorldConfig

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE


class _Parser(argparse.ArgumentParser):
    """argparse that reports usage errors as one line (no usage block) with exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def summary(world: WorldConfig) -> str:
    """A human-readable summary: entities, sensors, markers, and which entity can see which."""
    lines = [
        f"world file: {world.source or '(in memory)'}",
        f"conventions: world {world.world_convention.value}, body {world.body_convention.value} (internal ENU/FLU)",
        f"fusion: edge_timeout {world.fusion.edge_timeout_s * 1000:.0f} ms, ema_alpha {world.fusion.ema_alpha:g},"
        f" weighting {world.fusion.weighting.value}",
        f"fingerprint: {world.fingerprint():08x}",
        f"{len(world.entities)} entities, {len(world.sensors)} sensors, {len(world.markers)} markers",
    ]
    for ent in world.entities:
        lines.append(f"  {ent.name}: {len(ent.sensors)} sensors, {len(ent.markers)} markers")
        for s in ent.sensors:
            p = s.T_entity_sensor.translation
            axis = s.T_entity_sensor.rotation.apply([0.0, 0.0, 1.0])
            lines.append(
                f"    sensor {s.name} (id {s.id}) at [{p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}] m,"
                f" looking along [{axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}]"
            )
        for mk in ent.markers:
            p = mk.T_entity_marker.translation
            lines.append(
                f"    marker {mk.id} ({mk.family}, {mk.size_m * 1000:.0f} mm) at [{p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}] m"
            )
    lines.append("who can see whom (a sensor of the first sees markers of the second):")
    has_markers = [e.name for e in world.entities if e.markers]
    for ent in world.entities:
        if ent.sensors:
            targets = [n for n in has_markers if n != ent.name]
            lines.append(f"  {ent.name} -> {', '.join(targets) if targets else '(no markers elsewhere)'}")
    from atlas_onboard.config import WORLD

    unseen = [e.name for e in world.entities if e.name != WORLD and not e.sensors and not e.markers]
    if unseen:
        lines.append(f"warning: entities with neither sensors nor markers can never be localized: {', '.join(unseen)}")
    return "\n".join(lines)


def _cmd_check_config(args: argparse.Namespace) -> int:
    from atlas_onboard.config import load_world, security_notes

    world = load_world(args.file)
    print(summary(world))
    for note in security_notes(args.file):
        print(note)
    return EXIT_OK


def _cmd_run(args: argparse.Namespace) -> int:
    from atlas_onboard.service.run import run_node

    return run_node(args.config, args.entity, args.record, args.record_max_mb, args.write_map)


_BUILT_IN = ("run", "check-config")  # the commands build_parser defines itself


def build_parser(every_command: bool = True) -> argparse.ArgumentParser:
    """The argument parser with every subcommand (``every_command``), or with the built-in ones only."""
    parser = _Parser(prog="atlas-onboard", description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--version", action="version", version=f"atlas-onboard {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("check-config", help="validate and summarise a world file")
    p.add_argument("file", help="path of the YAML world file")
    p.set_defaults(func=_cmd_check_config)

    p = sub.add_parser("run", help="run the node of one entity (the service)")
    p.add_argument("--config", required=True, type=Path, help="world file with a nodes section")
    p.add_argument("--entity", help="entity whose node this is (default: the only one with node settings)")
    p.add_argument("--record", type=Path, metavar="DIR", help="record the cameras as the node flies (for `map`)")
    p.add_argument("--record-max-mb", type=float, metavar="MB", help="cap on the recordings in DIR (default 2000)")
    p.add_argument(
        "--write-map",
        type=Path,
        metavar="PATH",
        help="refine the world markers live; write the refined world file at exit",
    )
    p.set_defaults(func=_cmd_run)
    if not every_command:
        return parser

    from atlas_onboard.cli.calibrate import add_commands as add_calibrate
    from atlas_onboard.cli.detect import add_commands as add_detector
    from atlas_onboard.cli.install import add_commands as add_install
    from atlas_onboard.cli.map import add_commands as add_mapping
    from atlas_onboard.cli.params import add_commands as add_params
    from atlas_onboard.cli.preflight import add_commands as add_preflight

    for plugin in _plugged_in():
        plugin.load()(sub)
    add_calibrate(sub)
    add_detector(sub)
    add_install(sub)
    add_params(sub)
    add_mapping(sub)
    add_preflight(sub)
    return parser


COMMANDS_GROUP = "atlas_onboard.commands"
"""Entry points of this group add subcommands (``add_commands(sub)``): the simulator's ``sim``, ``demo``
and ``sim-autopilot``, declared in ``pyproject.toml``, so that the command line never imports the simulator."""


def _plugged_in() -> list[metadata.EntryPoint]:
    """The installed package's :data:`COMMANDS_GROUP` entry points, in the order declared (none when the
    package is not installed, as when its source tree is on the path)."""
    try:
        points = metadata.distribution("atlas-onboard").entry_points
    except metadata.PackageNotFoundError:
        return []
    return [p for p in points if p.group == COMMANDS_GROUP]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: parse ``argv``, run the subcommand, map known errors to one line and exit status 2.

    A reader that closes the pipe early (``atlas-onboard check-config FILE | head -1``) ends the
    command quietly with status 141 (as SIGPIPE would); Ctrl-C with one line and status 130.
    """
    try:
        try:
            try:
                code = _main(argv)
            except SystemExit as exc:  # argparse's --help, --version and usage errors
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else EXIT_USAGE)
            sys.stdout.flush()  # here, not at exit, where a closed pipe could only be reported
            return code
        except BrokenPipeError:
            # Python's recipe: point stdout at /dev/null so the interpreter's final flush is silent.
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            return EXIT_BROKEN_PIPE
    except KeyboardInterrupt:
        sys.stderr.write("atlas-onboard: interrupted\n")
        return EXIT_INTERRUPTED


def _main(argv: Sequence[str] | None) -> int:
    # The service (started by systemd, and by the simulator for every drone) needs none of the other
    # commands' modules, whose imports (OpenCV, scipy.optimize) would only slow its start.
    words = [a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-")]
    parser = build_parser(every_command=not words or words[0] not in _BUILT_IN)
    args = parser.parse_args(argv)
    level = (logging.INFO if args.command in ("run", "sim") else logging.WARNING) - 10 * min(args.verbose, 1)
    logging.basicConfig(level=level, stream=sys.stderr, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args))
    except AtlasError as exc:
        sys.stderr.write(f"atlas-onboard: error: {exc}\n")
        return EXIT_USAGE
