"""The ``drivetrack`` command line: discovers one subcommand per module of drivetrack.commands."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import drivetrack
import drivetrack.commands as _commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="drivetrack",
        description="Turn Waymo Open Dataset v2 driving logs into long-range point-track "
                    "annotations and publish them as versioned, validated dataset releases.")
    parser.add_argument("--version", action="version", version=f"drivetrack {drivetrack.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{_commands.__name__}.{info.name}")
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
