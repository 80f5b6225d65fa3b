"""The `companion` command: one sub-command per module, imported on use.

The dispatcher knows every sub-command's name and one-line help without
importing its module, and imports only the chosen one: ``companion --help``
loads no numpy, OpenCV, filterpy or pymavlink. Each sub-command module exposes
``configure_parser(parser)`` and ``main(args) -> int``.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
from types import ModuleType

# name -> (module, one-line help)
COMMANDS = {
    "run": ("companion.cli.run", "run the positioning daemon (default: bundled replay to udpout:127.0.0.1:14550)"),
    "markers": ("companion.cli.markers", "write printable RS markers (PNG, SVG, PDF sheets)"),
    "detect": ("companion.cli.detect", "detect RS markers in images: one line per image (JSON with --json)"),
    "localize": ("companion.cli.localize", "print the per-frame camera pose of a sequence (no filtering)"),
    "simulate": ("companion.cli.simulate", "render a synthetic camera sequence with ground truth"),
    "calibrate": ("companion.cli.calibrate", "calibrate a camera from ChArUco or chessboard views (images, videos or live)"),
    "report": ("companion.cli.report", "write an HTML flight report (plots) of a recorded flight"),
    "survey": ("companion.cli.survey", "build a facility map from walk-through footage and a few measured anchors"),
    "map": ("companion.cli.map", "check a facility map against a walk-through (markers that moved)"),
    "check-fc": ("companion.cli.check_fc", "read the flight controller's vision parameters and judge them"),
    "sitl-home": ("companion.cli.sitl_home", "print the --home LAT,LON,ALT,HEADING that starts a simulator at "
                  "the config's start position"),
}


class CommandUnavailable(RuntimeError):
    """A sub-command whose module cannot be imported (a missing dependency, a broken install)."""


def load_command(name: str) -> ModuleType:
    """Import the module of sub-command ``name``; CommandUnavailable names the module and what is missing."""
    module_name = COMMANDS[name][0]
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        missing = f"the package providing {error.name!r} is not installed" if error.name else str(error)
        raise CommandUnavailable(f"companion {name}: cannot import {module_name}: {missing} "
                                 "(reinstall companion with pip to get its dependencies)") from None
    except ImportError as error:
        raise CommandUnavailable(f"companion {name}: cannot import {module_name}: {error}") from None


def build_parser(command: str | None = None, module: ModuleType | None = None) -> argparse.ArgumentParser:
    """Every sub-command's name and help; the options of ``command`` alone, from its imported ``module``."""
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        sub_parser = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            module.configure_parser(sub_parser)
    return parser


# `companion run` is a service: a stop (SIGTERM) or a hangup (SIGHUP) while its modules import (a second or more
# on a small computer) and its config loads, before it has handlers of its own, would end it with 143 or 129 and
# not a word. Meanwhile they are noted here (``start_signals``), and `run` handles them once it can log:
# a stop ends it cleanly (exit 0), a hangup is said and changes nothing, as later. So is SIGINT when it came
# ignored (`companion run &` in a script): `run` stops on it once started, and it was lost before.
START_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
start_signals: list[int] = []


@contextlib.contextmanager
def signals_noted_while_starting(command: str | None):
    """For `companion run`: SIGTERM and SIGHUP (and SIGINT if it came ignored) noted in ``start_signals`` (not
    their default: the end of the process) until `run` installs its own handlers; the previous handlers back afterwards (``cli.main`` called
    in-process, by a test)."""
    previous = {}
    if command == "run":
        noted = START_SIGNALS + ((signal.SIGINT,) if signal.getsignal(signal.SIGINT) is signal.SIG_IGN else ())
        try:
            previous = {sig: signal.signal(sig, lambda signum, _frame: start_signals.append(signum))
                        for sig in noted}
        except ValueError:  # not the main thread: signals are not ours to handle
            previous = {}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        start_signals.clear()


def discard_stdout() -> None:
    """Point stdout at /dev/null: its reader is gone, and flushing what is left at exit would raise again."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # No option comes before the sub-command: a known name in first place is the chosen one.
    command = argv[0] if argv and argv[0] in COMMANDS else None
    try:
        with signals_noted_while_starting(command):
            return _run(command, argv)
    except KeyboardInterrupt:  # Ctrl-C at any point, the sub-command's imports included
        print(f"companion{f' {command}' if command else ''}: interrupted", file=sys.stderr)
        return 130


def program() -> int:
    """The ``companion`` program (its console script, ``python -m companion``): ``main``, after which, for `run`,
    a stop signal while the process ends (the summary logged, the threads finishing) changes nothing: the
    second SIGTERM of an impatient stop ended a cleanly stopped daemon with 143."""
    code = main()
    if sys.argv[1:2] == ["run"]:
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, signal.SIG_IGN)
    return code


def _run(command: str | None, argv: list[str]) -> int:
    """Parse ``argv`` and run ``command``; what a command raises becomes one line and an exit status."""
    try:
        module = load_command(command) if command else None
    except CommandUnavailable as error:
        print(error, file=sys.stderr)
        return 1
    parser = build_parser(command, module)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    from companion.cli.output import OutputError

    try:
        return int(module.main(args) or 0)
    except OutputError as error:
        print(f"companion {command}: {error}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader went away (`companion detect ... | head`): stop quietly, as a shell tool does
        discard_stdout()
        return 128 + signal.SIGPIPE
    except OSError as error:
        # a file that vanished or a disk that filled up mid-way: one line, not a traceback
        where = f"{error.filename}: " if error.filename else ""
        print(f"companion {command}: {where}{error.strerror or error}", file=sys.stderr)
        return 1


    sys.exit(program())
