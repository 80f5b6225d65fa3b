"""The `companion` dispatcher: it imports only the chosen sub-command, and a sub-command
that cannot be imported is a clear error, not a gap in the menu.

Imports are inspected in a fresh interpreter (a subprocess), where ``sys.modules``
holds exactly what the command line loaded.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from companion import cli

REPO = Path(__file__).resolve().parents[1]
HEAVY = ("numpy", "cv2", "filterpy", "pymavlink", "scipy")
DAEMON_ONLY = ("filterpy", "pymavlink", "companion.daemon.service")

# Runs the dispatcher as `companion ARGS...` (after optional set-up code), then prints
# on its last stdout line the JSON list of modules loaded, and exits with its status.
PROBE = """
import json, sys
from companion import cli
{setup}
try:
    status = cli.main(sys.argv[1:])
except SystemExit as stop:
    status = stop.code
print(json.dumps(sorted(sys.modules)))
sys.exit(status)
"""


@dataclass(frozen=True)
class Outcome:
    status: int
    modules: set[str]  # every module loaded, when the command returned
    stdout: str
    stderr: str


def run_dispatcher(args: list[str], setup: str = "", extra_path: Path | None = None) -> Outcome:
    """`companion ARGS...` in a fresh interpreter."""
    paths = [str(REPO)] + ([str(extra_path)] if extra_path else [])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
    result = subprocess.run([sys.executable, "-c", PROBE.format(setup=setup), *args],
                            capture_output=True, text=True, env=env, timeout=60)
    stdout, modules = result.stdout.rstrip("\n").rsplit("\n", 1) if "\n" in result.stdout.strip() \
        else ("", result.stdout)
    return Outcome(result.returncode, set(json.loads(modules)), stdout, result.stderr)


def cli_modules(outcome: Outcome) -> set[str]:
    """The sub-command modules imported (the shared output-path checks are no sub-command)."""
    commands = {module for module, _ in cli.COMMANDS.values()}
    return {m for m in outcome.modules if m in commands}


def test_top_level_help_lists_every_command_and_imports_none_of_them():
    outcome = run_dispatcher(["--help"])
    assert outcome.status == 0
    assert not outcome.modules & set(HEAVY), outcome.modules & set(HEAVY)
    assert not cli_modules(outcome)
    listed = " ".join(outcome.stdout.split())  # argparse wraps long help lines
    for name, (_, help_line) in cli.COMMANDS.items():
        assert f"{name} {help_line}" in listed


def test_a_sub_command_imports_its_own_module_only():
    outcome = run_dispatcher(["markers", "--help"])
    assert outcome.status == 0 and outcome.stdout.startswith("usage: companion markers ")
    assert cli_modules(outcome) == {"companion.cli.markers"}
    assert not outcome.modules & set(DAEMON_ONLY), outcome.modules & set(DAEMON_ONLY)
    outcome = run_dispatcher(["run", "--help"])
    assert outcome.status == 0
    assert cli_modules(outcome) == {"companion.cli.run"}
    assert set(DAEMON_ONLY) <= outcome.modules  # the control: the daemon's command does load them


@pytest.mark.parametrize("name", sorted(cli.COMMANDS))
def test_every_sub_command_imports_and_has_its_own_help(name, capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main([name, "--help"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: companion {name} ")


def test_no_command_prints_the_menu_and_fails():
    outcome = run_dispatcher([])
    assert outcome.status == 2 and "COMMAND" in outcome.stdout and not cli_modules(outcome)


@pytest.mark.parametrize("body, named", [
    ("import companion_missing_dependency_xyz\n", "the package providing 'companion_missing_dependency_xyz' is not installed"),
    ("from json import no_such_function\n", "cannot import name 'no_such_function'"),
])
@pytest.mark.parametrize("args", [["broken"], ["broken", "--help"]])
def test_a_sub_command_that_cannot_be_imported_is_a_clear_error(tmp_path, body, named, args):
    (tmp_path / "broken_command.py").write_text(body)
    setup = "cli.COMMANDS['broken'] = ('broken_command', 'a command whose module cannot be imported')"
    outcome = run_dispatcher(args, setup=setup, extra_path=tmp_path)
    assert outcome.status == 1
    lines = outcome.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in outcome.stderr, outcome.stderr
    assert lines[0].startswith("companion broken: cannot import broken_command: ")
    assert named in lines[0]
    menu = run_dispatcher(["--help"], setup=setup, extra_path=tmp_path)
    assert menu.status == 0 and "a command whose module cannot be imported" in menu.stdout  # still in the menu


@pytest.mark.parametrize("args", [["slow"], ["slow", "--help"]])
def test_ctrl_c_while_a_sub_command_is_still_importing_is_one_line_and_130(tmp_path, args):
    """A sub-command's imports (scipy, matplotlib) take a second on a small computer: Ctrl-C then is no traceback."""
    (tmp_path / "slow_command.py").write_text("raise KeyboardInterrupt  # as Ctrl-C during a long import\n")
    setup = "cli.COMMANDS['slow'] = ('slow_command', 'a command interrupted while it imports')"
    outcome = run_dispatcher(args, setup=setup, extra_path=tmp_path)
    assert outcome.status == 130 and outcome.stderr == "companion slow: interrupted\n", outcome.stderr
