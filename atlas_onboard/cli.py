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
from pathlib import Path

from atlas_onboard import __version__
from atlas_onboard.errors import AtlasError

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE


class _Parser(argparse.ArgumentParser):
    """argparse that reports usage errors as one line (no usage block) with exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def _cmd_check_config(args: argparse.Namespace) -> int:
    from atlas_onboard.config import load_world, security_notes, summary

    world = load_world(args.file)
    print(summary(world))
    for note in security_notes(args.file):
        print(note)
    return EXIT_OK


def _cmd_run(args: argparse.Namespace) -> int:
    from atlas_onboard.service_run import run_node

    return run_node(args.config, args.entity, args.record, args.record_max_mb)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
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
    p.set_defaults(func=_cmd_run)

    from atlas_onboard.detector.commands import add_commands as add_detector
    from atlas_onboard.install import add_commands as add_install
    from atlas_onboard.mapping.command import add_commands as add_mapping
    from atlas_onboard.params import add_commands as add_params
    from atlas_onboard.sim.command import add_commands as add_sim
    from atlas_onboard.sim.demo import add_commands as add_demo

    add_sim(sub)
    add_demo(sub)
    add_detector(sub)
    add_install(sub)
    add_params(sub)
    add_mapping(sub)
    return parser


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
    parser = build_parser()
    args = parser.parse_args(argv)
    level = (logging.INFO if args.command in ("run", "sim") else logging.WARNING) - 10 * min(args.verbose, 1)
    logging.basicConfig(level=level, stream=sys.stderr, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args))
    except AtlasError as exc:
        sys.stderr.write(f"atlas-onboard: error: {exc}\n")
        return EXIT_USAGE
