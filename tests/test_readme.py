"""The README's commands: its test command is the one .ci/run runs, and every usdeform command it shows parses."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from usdeform.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _commands(block: str) -> list[str]:
    """The commands of a bash block, continuation lines joined, comments dropped."""
    joined = block.replace("\\\n", " ")
    return [line.split("   #")[0].strip() for line in joined.splitlines() if line.strip()]


FIRST_BLOCK = _commands(re.search(r"```bash\n(.*?)```", README, re.S).group(1))
COMMAND_LINE = re.search(r"## Command line.*?```bash\n(.*?)```", README, re.S)


def test_the_first_screen_shows_install_and_demo_then_the_ci_test_command() -> None:
    install_and_demo, tests = FIRST_BLOCK
    assert install_and_demo.startswith("pip install . && usdeform demo --output ")
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    # `|| exit 1`: under set -e a failure inside an && list other than its last command would not stop .ci/run
    assert f"{tests} || exit 1" in ci_lines, (tests, ci_lines)
    picture = re.search(r"!\[[^]]*\]\(([^)]+\.png)\)", README[: README.index("## ")])
    assert picture and (ROOT / picture.group(1)).stat().st_size > 10_000


@pytest.mark.parametrize(
    "command", [c for c in _commands(COMMAND_LINE.group(1)) if c.startswith("usdeform ")] if COMMAND_LINE else []
)
def test_every_command_line_example_parses(command: str) -> None:
    arguments = shlex.split(command)[1:]
    parsed = build_parser().parse_args(arguments)
    assert callable(parsed.run)


def test_every_command_has_an_example() -> None:
    assert COMMAND_LINE
    shown = {shlex.split(c)[1] for c in _commands(COMMAND_LINE.group(1)) if c.startswith("usdeform ")}
    parser = build_parser()
    commands = next(a for a in parser._actions if a.dest == "command").choices
    assert set(commands) <= shown, set(commands) - shown


def test_every_experiment_has_an_example() -> None:
    assert COMMAND_LINE
    shown = {shlex.split(c)[2] for c in _commands(COMMAND_LINE.group(1)) if c.startswith("usdeform experiment ")}
    commands = next(a for a in build_parser()._actions if a.dest == "command").choices
    names = next(a for a in commands["experiment"]._actions if a.dest == "name").choices
    assert set(names) <= shown, set(names) - shown


def test_the_documentation_site_opens_with_the_same_two_commands() -> None:
    index = (ROOT / "docs" / "index.md").read_text()
    assert _commands(re.search(r"```bash\n(.*?)```", index, re.S).group(1)) == FIRST_BLOCK
