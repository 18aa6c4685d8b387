"""The systemd units in deploy/ run commands this version accepts: each ``ExecStart``
parses with the command's own parser, so a renamed option breaks this test, not a site's
service; each stops by SIGTERM and is not restarted on exit status 2 (bad input: a
restart would not fix it)."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

from calibration.cli import build_parser as twin_parser
from daq.cli import build_parser as daq_parser

DEPLOY = Path(__file__).parents[1] / "deploy"
UNITS = sorted(DEPLOY.glob("*.service"))


def _exec_start(unit: Path) -> list[str]:
    lines = [x for x in unit.read_text(encoding="utf-8").splitlines() if x.startswith("ExecStart=")]
    assert len(lines) == 1, f"{unit.name}: {len(lines)} ExecStart lines"
    return shlex.split(lines[0].removeprefix("ExecStart="))


def test_every_unit_is_checked() -> None:
    assert {u.name for u in UNITS} >= {"daq.service", "daq-router.service", "twin.service"}


@pytest.mark.parametrize("unit", UNITS, ids=lambda u: u.name)
def test_the_unit_command_parses(unit: Path) -> None:
    program, *argv = _exec_start(unit)
    name = Path(program).name
    assert name in ("daq", "twin"), f"{unit.name}: runs {program}"
    parser = daq_parser() if name == "daq" else twin_parser(argv[0])
    args = parser.parse_args(argv)  # argparse exits 2 on an option it does not know
    assert args.command == argv[0]
    text = unit.read_text(encoding="utf-8")
    assert "KillSignal=SIGTERM" in text and "RestartPreventExitStatus=2" in text
