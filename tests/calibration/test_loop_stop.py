"""The closed loop says why it stopped, and names the best candidate left.

Three honest reasons (calibration.effects.closed_loop.StopReason): the maximum number of effects
reached (``--max-effects``), candidates undone by the validation re-check, none significant.
Effects come from the emulator's own parameters; the twin gets no mass model.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from functools import cache
from typing import Any

import numpy as np
import pytest

from benchmarks.bench_attribution import emulated, twin_description
from calibration.effects.closed_loop import ClosedLoopResult, LoopSettings, run_closed_loop
from calibration.effects.identification_report import closed_loop_document
from calibration.identify.campaign_files import write_campaign


@cache
def run(case: str, max_effects: int = 6) -> ClosedLoopResult:
    data = emulated("kr500", case, 1)
    desc = twin_description(data.cell.nominal, "none")
    return run_closed_loop(desc, data.campaign, settings=LoopSettings(max_effects=max_effects))


def stopped(res: ClosedLoopResult) -> dict[str, Any]:
    """report.json's ``closed_loop.stopped`` (the Markdown is checked through the CLI)."""
    return dict(closed_loop_document(res, 6)["stopped"])


def test_undone_candidates_are_the_reason_not_insignificance():
    """An error only the identification poses have (added to them alone) is significant
    there and refuted by the validation poses: every step is undone. With at most two tried,
    the loop says that is why it stopped, instead of calling the candidates insignificant,
    and names the best candidate left; with the default four, fewer are significant, and the
    stop for want of significance still counts the ones undone."""
    clean = emulated("kr500", "clean", 1).campaign
    idm = clean.mask("identify")
    xyz = clean.xyz_mm.copy()
    xyz[idm, 0] += 0.05 * np.sin(2 * clean.q_rad[idm, 0])
    fooled = dataclasses.replace(clean, xyz_mm=xyz)
    desc = twin_description(emulated("kr500", "clean", 1).cell.nominal, "none")
    res = run_closed_loop(desc, fooled, settings=LoopSettings(max_rejected=2))
    assert res.added == () and len(res.rejected) == 2
    assert res.stop.code == "set_aside"
    doc = stopped(res)
    assert "2 significant candidate(s) were undone by the validation re-check" in doc["reason"]
    assert "no candidate is significant" not in doc["reason"]
    best = res.stop.best_remaining
    assert best is not None and best.label not in {r.label for r in res.rejected}
    assert doc["best_remaining"]["effect"] == best.label
    default = run_closed_loop(desc, fooled)
    assert default.added == () and default.rejected
    n = len(default.rejected)
    if default.stop.code == "none_significant":
        assert f"({n} set aside by the validation re-check)" in default.stop.text
    else:
        assert default.stop.code == "set_aside" and n == default.settings.max_rejected


def test_the_maximum_is_the_reason_and_the_next_effect_is_named():
    """Gravity and a cyclic error of the elbow: with one effect allowed, gravity is in and
    the cyclic error, still significant, is named as the best candidate left; with none
    allowed, gravity is."""
    one = run("gravity+cyclic", 1)
    assert [s.kind for s in one.added] == ["gravity_deflection"]
    assert one.stop.code == "max_effects" and "(1)" in one.stop.text
    best = one.stop.best_remaining
    assert best is not None and best.significant
    assert (best.spec.kind, best.spec.joint, best.spec.order) == ("joint_harmonic", 3, 2)
    assert stopped(one)["best_remaining"]["effect"] == best.label
    none = run("gravity+cyclic", 0)
    assert none.added == () and none.stop.code == "max_effects"
    assert none.stop.best_remaining is not None
    assert none.stop.best_remaining.spec.kind == "gravity_deflection"


def test_clean_data_stops_for_want_of_significance_and_names_its_best():
    res = run("clean")
    assert res.added == () and res.stop.code == "none_significant"
    best = res.stop.best_remaining
    assert best is not None and not best.significant and best.n_parameters > 0
    assert stopped(res)["reason"] == "no remaining candidate is significant"


def test_all_effects_in_stops_for_want_of_significance():
    res = run("gravity+cyclic")
    assert len(res.added) == 2 and res.stop.code == "none_significant"
    assert res.stop.best_remaining is not None and not res.stop.best_remaining.significant


def twin(*args: str, cwd=None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "calibration.cli", *args],
        capture_output=True, text=True, timeout=120, cwd=cwd,
    )  # fmt: skip


def test_max_effects_on_twin_identify(tmp_path):
    data = emulated("kr500", "gravity+cyclic", 1)
    path = tmp_path / "campaign.csv"
    write_campaign(path, data.campaign)
    out, rep = tmp_path / "cal.toml", tmp_path / "report"
    proc = twin("identify", "--robot", "kr500", "--data", str(path), "--out", str(out),
                "--report", str(rep), "--max-effects", "1", "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "stopped: the maximum number of effects (1) is reached" in proc.stdout
    assert "best remaining: cyclic error of joint 3 (harmonic 2)" in proc.stdout
    md = (rep / "report.md").read_text()
    assert "Stopped: the maximum number of effects (1) is reached" in md
    assert "best remaining: cyclic error of joint 3 (harmonic 2), significant" in md
    assert out.read_text().count("[[effect]]") == 1


@pytest.mark.parametrize("command", ["identify", "run"])
@pytest.mark.parametrize("value", ["-1", "two", "1.5"])
def test_bad_max_effects_is_refused_in_one_line(tmp_path, command, value):
    args = ["--robot", "kr500", "--out", "o", "--max-effects", value]
    if command == "identify":
        args += ["--data", "campaign.csv"]
    else:
        args += ["--replay", "x.mcap"]
    proc = twin(command, *args, cwd=tmp_path)
    err = proc.stderr.strip()
    assert proc.returncode == 2 and "Traceback" not in err, err
    assert len(err.splitlines()) == 1 and "--max-effects" in err, err
    assert not (tmp_path / "o").exists()
