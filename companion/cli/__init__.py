"""The `companion` command: one sub-command per module, imported on use.

Each sub-command module exposes ``configure_parser(parser)`` and
``main(args) -> int``.
"""
from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = {
    "run": ("companion.cli.run", "run the positioning daemon (default: bundled replay to udpout:127.0.0.1:14550)"),
    "markers": ("companion.cli.markers", "write printable RS markers (PNG, SVG, PDF sheets)"),
    "detect": ("companion.cli.detect", "detect RS markers in images and print JSON lines"),
    "localize": ("companion.cli.localize", "print the per-frame camera pose of a sequence (no filtering)"),
    "simulate": ("companion.cli.simulate", "render a synthetic camera sequence with ground truth"),
    "calibrate": ("companion.cli.calibrate", "calibrate a camera from chessboard images"),
}


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, object]]:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = {}
    for name, (module_name, help_text) in COMMANDS.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            if error.name != module_name:
                raise
            continue
        modules[name] = module
        module.configure_parser(sub.add_parser(name, help=help_text, description=help_text))
    return parser, modules


def main(argv: list[str] | None = None) -> int:
    parser, modules = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    return int(modules[args.command].main(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
