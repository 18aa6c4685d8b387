"""The twin following the robot (issue 28): the drifting emulator, the tracker, twin track.

The emulator moves its truth during a production run (thermal growth, base creep, a step);
the twin gets the campaign and the checks a user would have and nothing else; accuracy is
judged against the emulator's own step times and the static model. The sweeps over 10 and
20 seeds are ``tests/test_tracking_acceptance.py`` (slow).
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.effects.calibrate import calibrate
from calibration.identify.campaign_files import write_campaign
from calibration.model.description import RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel, identification_jacobian
from calibration.model.point_jacobian import point_jacobian
from calibration.twin.step_test import StepTest, false_alarm_rate
from calibration.twin.tracking import (
    effect_offsets,
    start_tracking,
    static_errors_mm,
    track_checks,
    track_update,
    tracking_setup,
)
from sim_devices.drift import CellDrift, drifted_tcp_mm
from sim_devices.pose_campaign import (
    CampaignSettings,
    CheckProgram,
    emulated_campaign,
    emulated_checks,
)

ROOT = Path(__file__).resolve().parents[2]
TWIN = [sys.executable, "-m", "calibration.cli"]
DRIFT = CellDrift(thermal=True, creep=True, steps=("tool_remount",))


def _scenario(seed: int, drift: CellDrift, hours: float = 8.0):
    nominal = load_robot("kr500")
    data = emulated_campaign(nominal, seed)
    checks = emulated_checks(data, seed, CheckProgram(hours=hours, drift=drift), CampaignSettings())
    cal = calibrate(nominal, data.campaign, effects=False)
    return data, checks, cal.description


def _track(desc: RobotDescription, checks):
    c = checks.checks
    setup = tracking_setup(desc)
    q = np.radians(c.q_deg)
    off = effect_offsets(desc, q, c.t_s)
    return setup, track_checks(setup, q, c.xyz_mm, off), static_errors_mm(setup, q, c.xyz_mm, off)


# -- the emulator ------------------------------------------------------------------------------
def test_the_campaign_is_the_same_with_and_without_a_production_run():
    data = emulated_campaign("kr500", 2)
    before = data.campaign.xyz_mm.copy()
    checks = emulated_checks(data, 2, CheckProgram(hours=1.0, drift=DRIFT), CampaignSettings())
    again = emulated_campaign("kr500", 2)
    assert np.array_equal(again.campaign.xyz_mm, before)
    t = checks.checks.t_s
    assert t[0] > data.campaign.t_s[-1] and np.all(np.diff(t) > 0)


def test_the_truth_moves_by_the_drift_alone():
    data = emulated_campaign("kr500", 4)
    model = data.cell.model
    q = data.q_true_rad[:20]
    program = CheckProgram(drift=CellDrift(thermal=True))
    draws = emulated_checks(data, 4, program, CampaignSettings()).draws
    still = drifted_tcp_mm(CellDrift(), draws, model, q, draws.start_s + 8 * 3600.0)
    assert np.allclose(still, data.cell.tcp_mm(q), atol=1e-9)
    warm = drifted_tcp_mm(program.drift, draws, model, q, draws.start_s + 8 * 3600.0)
    moved = np.linalg.norm(warm - still, axis=1)
    # 40 ppm of a ~3 m arm, gains 0.5..1.5: tens of µm to ~0.2 mm
    assert 0.01 < moved.max() < 0.3


def test_one_poses_jacobian_is_the_identification_jacobian():
    rng = np.random.default_rng(0)
    for name in ("kr500", "kr210_r3100", "hp20d"):
        model = KinematicModel.from_description(load_robot(name))
        model = model.with_parameters(model.parameter_vector() + rng.normal(0, 1e-2, 39))
        for q in rng.uniform(-3.0, 3.0, (5, model.n_joints)):
            p, jac = point_jacobian(model, q)
            p_ref, jac_ref = identification_jacobian(model, q)
            assert np.allclose(p, p_ref, rtol=0, atol=1e-9)
            assert np.allclose(jac, jac_ref, rtol=0, atol=1e-9)


# -- the tracker --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def drifting():
    _, checks, desc = _scenario(3, DRIFT)
    return checks, desc, _track(desc, checks)


def test_drift_and_a_step_are_followed_and_the_step_reported(drifting):
    checks, _, (_, run, static) = drifting
    step_t = checks.draws.step_times_s["tool_remount"]
    step_row = int(np.searchsorted(checks.checks.t_s, step_t))
    assert run.error_mm.mean() <= 0.5 * static.mean()
    assert len(run.steps) == 1, run.steps
    detected, onset = run.steps[0]
    assert 0 <= detected - step_row < 5 and onset == step_row
    pre = run.error_mm[step_row - 20 : step_row].mean()
    after = run.error_mm[step_row:]
    assert any(after[i : i + 5].mean() <= 1.5 * pre for i in range(20))


def test_a_clean_run_costs_nothing_and_raises_nothing():
    _, checks, desc = _scenario(5, CellDrift())
    _, run, static = _track(desc, checks)
    assert run.steps == ()
    assert "step" not in run.states and "alarm" not in run.states
    assert run.error_mm.mean() <= 1.05 * static.mean()


def test_a_prediction_uses_nothing_of_its_own_point_or_later_rows(drifting):
    checks, desc, (setup, run, _) = drifting
    c = checks.checks
    q = np.radians(c.q_deg[:60])
    off = effect_offsets(desc, q, c.t_s[:60])
    changed = c.xyz_mm[:60].copy()
    changed[40:] += 5.0  # row 40's point and every later one
    other = track_checks(setup, q, changed, off)
    assert np.array_equal(other.predicted_mm[:41], run.predicted_mm[:41])
    assert not np.allclose(other.predicted_mm[41:], run.predicted_mm[41:60])


def test_an_update_is_a_pure_function_of_its_state(drifting):
    checks, _, (setup, _, _) = drifting
    c = checks.checks
    start = start_tracking(setup)
    q = np.radians(c.q_deg[0])
    a, step_a = track_update(setup, start, q, c.xyz_mm[0])
    b, step_b = track_update(setup, start, q, c.xyz_mm[0])
    assert np.array_equal(a.theta, b.theta) and step_a.error_mm == step_b.error_mm
    assert np.array_equal(start.theta, np.zeros(len(setup.names)))


def test_a_single_wild_point_is_no_step(drifting):
    checks, desc, (setup, _, _) = drifting
    c = checks.checks
    q = np.radians(c.q_deg[:40])
    pts = c.xyz_mm[:40].copy()
    pts[20] += 3.0
    run = track_checks(setup, q, pts, effect_offsets(desc, q, c.t_s[:40]))
    assert run.steps == ()


def test_the_step_test_false_alarm_rate_is_below_one_in_ten_thousand_checks():
    assert false_alarm_rate(StepTest(), 2000, 200) < 1e-4
    # and a test that fires on everything is seen to
    assert false_alarm_rate(StepTest(threshold=0.5, cap=1.0), 200, 20) > 1e-3


# -- twin track -------------------------------------------------------------------------------
def twin(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [*TWIN, *args], cwd=cwd, capture_output=True, text=True, timeout=120, env=env
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("track")
    data = emulated_campaign("kr500", 6, CampaignSettings(n_identify=60, n_validate=30))
    checks = emulated_checks(data, 6, CheckProgram(hours=2.0, drift=DRIFT), CampaignSettings())
    write_campaign(root / "campaign.csv", data.campaign)
    write_campaign(root / "checks.csv", checks.checks)
    proc = twin(root, "identify", "--robot", "kr500", "--data", "campaign.csv",
                "--out", "cal.toml", "--no-effects", "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return root


def test_twin_track_writes_the_contracted_columns_and_a_readable_model(files, tmp_path):
    out = tmp_path / "tracked.csv"
    proc = twin(files, "track", "--model", "cal.toml", "--data", "checks.csv", "--out", str(out),
                "--alarm-mm", "0.1", "--out-model", str(tmp_path / "m.toml"),
                "--report", str(tmp_path / "rep"))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.reader(out.open()))
    head = rows[0]
    lead = "pose,t_s,x_mm,y_mm,z_mm,pred_x_mm,pred_y_mm,pred_z_mm,err_mm,state,lambda"
    assert head[:11] == lead.split(",")
    names = head[11::2]
    assert head[12::2] == [f"{n}_se" for n in names]
    assert "base.x_mm" in names and "joint3.length_scale" in names
    checks = list(csv.reader((files / "checks.csv").open()))
    assert len(rows) == len(checks)
    assert [r[0] for r in rows[1:]] == [r[0] for r in checks[1:]]
    assert {r[9] for r in rows[1:]} <= {"following", "step", "alarm"}
    assert "alarm" in {r[9] for r in rows[1:]}  # the remount moves the TCP 0.3 mm
    for r in rows[1:]:
        assert all(len(v.split(".")[1]) >= 6 for v in r[1:9] + r[10:])
    model = load_robot(tmp_path / "m.toml")
    assert model.tracking is not None
    assert (tmp_path / "rep" / "report.md").read_text().count("tracked, shuffled order") == 1
    predicted = twin(files, "predict", "--model", str(tmp_path / "m.toml"),
                     "--data", "checks.csv", "--out", str(tmp_path / "p.csv"))  # fmt: skip
    assert predicted.returncode == 0, predicted.stderr


def test_twin_track_params_choose_the_set_and_set_is_optional(files, tmp_path):
    out = tmp_path / "t.csv"
    _rewrite(
        files / "checks.csv", tmp_path / "noset.csv", lambda rows: [r[:1] + r[2:] for r in rows]
    )
    proc = twin(files, "track", "--model", "cal.toml", "--data", str(tmp_path / "noset.csv"),
                "--out", str(out), "--params", "base.x_mm,joint2.a_mm")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert next(csv.reader(out.open()))[11:] == [
        "base.x_mm", "base.x_mm_se", "joint2.a_mm", "joint2.a_mm_se",
    ]  # fmt: skip


def _rewrite(src: Path, dst: Path, change) -> None:
    rows = list(csv.reader(src.open()))
    rows = change(rows)
    with dst.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)


def _swap(rows):
    rows[5], rows[6] = rows[6], rows[5]
    return rows


def _repeat(rows):
    rows[6][2] = rows[5][2]
    return rows


def _nan(rows):
    rows[4][rows[0].index("y_mm")] = "nan"
    return rows


def _metres(rows):
    for r in rows[1:]:
        for c in ("x_mm", "y_mm", "z_mm"):
            r[rows[0].index(c)] = str(float(r[rows[0].index(c)]) / 1000.0)
    return rows


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (_swap, ["line", "t_s", "time order"]),
        (_repeat, ["t_s", "repeats"]),
        (_nan, ["y_mm", "finite"]),
        (_metres, ["x_mm", "metres"]),
    ],
)
def test_twin_track_refuses_bad_checks(files, tmp_path, change, words):
    _rewrite(files / "checks.csv", tmp_path / "bad.csv", change)
    _refused(files, tmp_path, ["--data", str(tmp_path / "bad.csv")], words)


def test_twin_track_refuses_an_unknown_parameter_and_an_untracked_model(files, tmp_path):
    _refused(files, tmp_path, ["--params", "base.x_mm,joint9.a_mm"], ["--params", "joint9.a_mm"])
    old = load_robot(files / "cal.toml")
    RobotDescription(old.name, old.joints, old.tool, old.base, old.home_deg).save(
        tmp_path / "old.toml"
    )
    _refused(files, tmp_path, ["--model", str(tmp_path / "old.toml")], ["old.toml", "[tracking]"])


def _refused(files: Path, tmp_path: Path, extra: list[str], words: list[str]) -> None:
    args = {"--model": "cal.toml", "--data": "checks.csv"}
    for k, v in zip(extra[::2], extra[1::2], strict=True):
        args[k] = v
    out = tmp_path / "out"
    flat = [x for kv in args.items() for x in kv]
    proc = twin(files, "track", *flat, "--out", str(out / "t.csv"),
                "--report", str(out / "rep"), "--out-model", str(out / "m.toml"))  # fmt: skip
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, err)
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for w in words:
        assert w.lower() in err.lower(), (w, err)
    assert not out.exists()


# -- the emulator's switches ------------------------------------------------------------------
def _sim(cwd: Path, module: str, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd, capture_output=True, text=True, timeout=120, env=env,
    )  # fmt: skip


def test_pose_campaign_writes_a_drifting_check_file_from_flags_and_cell_toml(tmp_path):
    (tmp_path / "cell.toml").write_text(
        '[effects.drift]\nthermal = true\nsteps = ["tracker_bump"]\n'
    )
    proc = _sim(tmp_path, "sim_devices.pose_campaign", "--seed", "2", "--out", "c.csv",
                "--checks", "k.csv", "--cell", "cell.toml", "--drift", "creep",
                "--check-hours", "1", "--check-every-min", "5", "--truth", "t.toml")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.reader((tmp_path / "k.csv").open()))
    assert len(rows) == 1 + 12 and rows[0][:3] == ["pose", "set", "t_s"]
    t = [float(r[2]) for r in rows[1:]]
    assert t == sorted(t)
    truth = (tmp_path / "t.toml").read_text()
    assert "thermal = true" in truth and "creep = true" in truth and "tracker_bump" in truth


def test_drift_needs_a_check_file_and_the_live_cell_drifts_from_its_config(tmp_path):
    (tmp_path / "cell.toml").write_text("[effects.drift]\ncreep = true\nspan_s = -1\n")
    proc = _sim(tmp_path, "sim_devices.pose_campaign", "--out", "c.csv", "--drift", "thermal")
    assert proc.returncode == 2 and "--checks" in proc.stderr
    assert not (tmp_path / "c.csv").exists()
    # the live cell takes [effects.drift] (tests/sim_devices/test_sim_live_drift.py), its
    # keys checked like every other
    live = _sim(tmp_path, "sim_devices.cli", "truth", "--config", "cell.toml", "--out", "t.toml")
    assert live.returncode == 2 and "[effects.drift]: key 'span_s'" in live.stderr, live.stderr
    assert not (tmp_path / "t.toml").exists()
    (tmp_path / "cell.toml").write_text('[effects.drift]\ncreep = true\nsteps = ["tracker_bump"]\n')
    live = _sim(tmp_path, "sim_devices.cli", "truth", "--config", "cell.toml", "--out", "t.toml")
    assert live.returncode == 0, live.stderr
    truth = (tmp_path / "t.toml").read_text()
    assert "[drift.draws.step_times_s]" in truth and "tracker_bump = " in truth
