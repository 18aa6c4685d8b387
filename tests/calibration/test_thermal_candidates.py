"""Thermal terms driven by a measured temperature (campaign.csv's optional ``temp_c``).

The emulator's arm expands with its own temperature history (a warm-up with the hall's
air-handling cycle on top, :func:`sim_devices.effects.arm_temperature_c`), and the
campaign writes that temperature with a sensor's noise. The twin is given the campaign
only: the loop must name the temperature-driven expansion and bring the held-out error
against the emulator's truth down. Without a ``temp_c`` column nothing changes; a bad one
is one clear line naming the file, the line and the column.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibration.cli import main
from calibration.effects.closed_loop import LoopSettings, campaign_effect_data, run_closed_loop
from calibration.effects.effect_base import EffectContext, EffectData, EffectSpec, ModelAtPoses
from calibration.effects.effect_candidates import candidate_effects
from calibration.effects.effect_kinds import KINDS, predict_points
from calibration.effects.model_effects import description_effects, predict_tcp
from calibration.errors import DataFileError
from calibration.identify.campaign_files import read_campaign, write_campaign
from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel, tcp_positions
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign

THERMAL = CampaignSettings(effects=UndeclaredEffects.named("thermal_expansion"))
TEMPERATURE_KINDS = {k for k, v in KINDS.items() if v.needs_temperature}


def _truth_error_mm(desc, data, stage):
    """Mean distance ``(mm)`` of a stage's validation predictions from the truth."""
    camp = data.campaign
    val = camp.mask("validate")
    ctx = EffectContext(desc, campaign_effect_data(desc, camp).subset(val))
    pred = predict_points(stage.model, stage.specs, stage.effect_values, ctx)
    return float(np.mean(np.linalg.norm(pred - data.true_prediction_mm[val], axis=1)))


@pytest.mark.parametrize(("robot", "seeds"), [("kr500", (1, 2)), ("hp20d", (1,))])
def test_loop_names_the_temperature_driven_expansion(robot, seeds):
    """Over seeds: the first effect added is the thermal expansion with the measured
    temperature, its coefficient near the emulator's 11.5 ppm/K, and the held-out error
    against the truth falls to under half the geometric model's (worst case reported)."""
    desc = load_robot(robot)
    ratios = []
    for seed in seeds:
        data = emulated_campaign(robot, seed, THERMAL)
        result = run_closed_loop(desc, data.campaign)
        added = result.added
        assert added and added[0].kind == "thermal_expansion", (seed, [s.label for s in added])
        assert all(s.kind not in ("length_drift", "cartesian_time") for s in added)
        kappa = float(result.final.values_of(added[0])[0])
        assert 7.0 < kappa < 16.0, (seed, kappa)
        before = _truth_error_mm(desc, data, result.geometric)
        after = _truth_error_mm(desc, data, result.final)
        ratios.append(after / before)
    assert max(ratios) < 0.5, ratios


def test_without_temp_c_nothing_changes(tmp_path):
    """No column: no temperature candidate and the file has no temp_c; a column that
    varies less than the threshold offers none either; a varying one adds exactly the
    temperature kinds, each with the median temperature as its reference."""
    desc = load_robot("kr500")
    clean = emulated_campaign("kr500", 3).campaign
    assert clean.temp_c is None
    path = tmp_path / "c.csv"
    write_campaign(path, clean)
    assert "temp_c" not in path.read_text().splitlines()[0]
    idm = clean.mask("identify")

    def offered(campaign):
        return candidate_effects(
            EffectContext(desc, campaign_effect_data(desc, campaign).subset(idm))
        )

    plain = offered(clean)
    assert not {s.kind for s in plain} & TEMPERATURE_KINDS
    flat = replace(clean, temp_c=np.full(len(clean), 22.0) + np.linspace(0.0, 0.1, len(clean)))
    assert offered(flat) == plain
    warm = replace(clean, temp_c=np.linspace(21.0, 24.0, len(clean)))
    with_temp = offered(warm)
    assert [s for s in with_temp if s.kind not in TEMPERATURE_KINDS] == plain
    extra = [s for s in with_temp if s.kind in TEMPERATURE_KINDS]
    assert {s.kind for s in extra} == TEMPERATURE_KINDS
    t_ref = round(float(np.median(warm.temp_c[idm])), 2)
    assert all(s.t_ref_c == t_ref for s in extra)


def test_calibrated_toml_keeps_the_term_and_predicts_at_t_ref(tmp_path):
    """The term goes to calibrated.toml with its reference temperature; a prediction
    without a temperature (twin predict's joints.csv has none) is the one at T_ref: the
    geometry alone; with the temperature it is the loop's own prediction."""
    desc = load_robot("kr500")
    data = emulated_campaign("kr500", 2, THERMAL)
    result = run_closed_loop(desc, data.campaign, settings=LoopSettings(max_effects=1))
    path = tmp_path / "calibrated.toml"
    result.calibrated_description(desc).save(path)
    model = load_robot(str(path))
    specs, values = description_effects(model)
    assert [s.kind for s in specs] == ["thermal_expansion"]
    assert specs[0].t_ref_c is not None and 21.0 < specs[0].t_ref_c < 25.0
    q = data.campaign.q_rad[:5]
    geometry = KinematicModel.from_description(model)
    np.testing.assert_allclose(predict_tcp(model, q), tcp_positions(geometry, q), atol=1e-9)
    camp = data.campaign.subset(np.arange(len(data.campaign)) < 5)
    ctx = EffectContext(model, campaign_effect_data(model, camp))
    loop = predict_points(result.final.model, result.final.specs, result.final.effect_values, ctx)
    np.testing.assert_allclose(predict_points(geometry, specs, values, ctx), loop, atol=1e-6)


@pytest.mark.parametrize(
    ("value", "says"),
    [
        ("295.15", "(kelvin? the column is in °C)"),
        ("nan", "is not a finite number"),
        ("warm", "is not a number"),
        ("-80", "is not a temperature in °C"),
    ],
)
def test_bad_temp_c_is_one_line_naming_file_line_and_column(tmp_path, capsys, value, says):
    data = emulated_campaign("kr500", 1, replace(THERMAL, n_identify=30, n_validate=5))
    good = tmp_path / "campaign.csv"
    write_campaign(good, data.campaign)
    lines = good.read_text().splitlines()
    fields = lines[3].split(",")
    fields[-1] = value
    lines[3] = ",".join(fields)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFileError, match="line 4") as exc:
        read_campaign(bad, 6)
    assert "column 'temp_c'" in str(exc.value) and says in str(exc.value)
    out = tmp_path / "out.toml"
    rc = main(["identify", "--robot", "kr500", "--data", str(bad), "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert str(bad) in err[0] and "line 4" in err[0] and "column 'temp_c'" in err[0]
    assert not out.exists()
    assert read_campaign(good, 6).temp_c is not None  # the good file reads


def test_regressors_match_grown_models_and_the_prediction_uses_temp_c():
    """Each temperature term against an independent computation: the model with its
    lengths grown, the tracker's points scaled; 0 at T_ref and without a temperature."""
    desc = load_robot("kr500")
    model = KinematicModel.from_description(desc)
    rng = np.random.default_rng(5)
    q = np.radians(rng.uniform(-40.0, 40.0, (12, 6)))
    temp = rng.uniform(19.0, 25.0, 12)
    data = EffectData.from_sequence(q, None, np.radians(desc.home), temp_c=temp)
    ctx, kin = EffectContext(desc, data), ModelAtPoses.of(model, q)
    every = slice(0, 12)
    rise = temp - 21.0
    spec = EffectSpec("thermal_expansion", joints=(1, 2, 3), t_ref_c=21.0)
    r = KINDS["thermal_expansion"].regressor(spec, ctx, every, kin)[:, :, 0]
    for i in range(12):
        x = model.parameter_vector()
        x[[0, 2, 5, 7, 10, 12]] *= 1.0 + 1e-6 * rise[i] * 10.0  # 10 ppm/K, links 1-3
        grown = tcp_positions(model.with_parameters(x), q[i : i + 1])[0]
        np.testing.assert_allclose(r[i] * 10.0, grown - kin.tcp_mm[i], atol=1e-9)
    spec = EffectSpec("length_temperature", joint=3, parameter="d", t_ref_c=21.0)
    r = KINDS["length_temperature"].regressor(spec, ctx, every, kin)[:, :, 0]
    np.testing.assert_allclose(r, kin.length_axis(3, "d") * rise[:, None], atol=1e-12)
    spec = EffectSpec("instrument_scale_temperature", t_ref_c=21.0)
    r = KINDS["instrument_scale_temperature"].regressor(spec, ctx, every, kin)[:, :, 0]
    np.testing.assert_allclose(r, kin.tcp_mm * 1e-6 * rise[:, None], atol=1e-12)
    at_ref = EffectContext(desc, replace(data, temp_c=np.full(12, 21.0)))
    unmeasured = EffectContext(desc, replace(data, temp_c=None))
    for c in (at_ref, unmeasured):
        assert not KINDS["instrument_scale_temperature"].regressor(spec, c, every, kin).any()


@pytest.fixture(scope="module")
def warm_model(tmp_path_factory):
    """A calibrated.toml with the loop's thermal expansion (kr500, seed 2) and its
    campaign: what a user has after ``twin identify`` on a warming arm."""
    from calibration.effects.calibrate import calibrate

    desc = load_robot("kr500")
    data = emulated_campaign("kr500", 2, THERMAL)
    loop = LoopSettings(max_effects=1)
    result = calibrate(desc, data.campaign, loop_settings=loop, learned=False)
    assert [e.kind for e in result.description.effects] == ["thermal_expansion"]
    path = tmp_path_factory.mktemp("warm") / "calibrated.toml"
    result.description.save(path)
    return path, data


def test_prediction_at_the_measured_temperature_follows_the_truth(warm_model):
    """``predict_tcp`` given each validation pose's ``temp_c`` is the loop's own
    prediction, and nearer the emulator's truth than the prediction at T_ref (the
    temperature left out) over a 3 K warm-up."""
    path, data = warm_model
    model = load_robot(str(path))
    camp = data.campaign
    val = camp.mask("validate")
    assert np.ptp(camp.temp_c[val]) > 1.0  # the validation poses span the warm-up
    truth = data.true_prediction_mm[val]
    warm = predict_tcp(model, camp.q_rad[val], camp.t_s[val], temp_c=camp.temp_c[val])
    at_ref = predict_tcp(model, camp.q_rad[val], camp.t_s[val])
    err_warm = np.mean(np.linalg.norm(warm - truth, axis=1))
    err_ref = np.mean(np.linalg.norm(at_ref - truth, axis=1))
    assert err_warm < 0.5 * err_ref, (err_warm, err_ref)
    with pytest.raises(ValueError):
        predict_tcp(model, camp.q_rad[val], temp_c=camp.temp_c[:2])  # one per pose


def _joints_csv(path, camp, rows, temperature):
    head = "pose,t_s," + ",".join(f"q{j}_deg" for j in range(1, 7))
    lines = [head + (",temp_c" if temperature else "")]
    for i in rows:
        fields = [camp.pose[i], f"{camp.t_s[i]:.3f}", *(f"{v:.6f}" for v in camp.q_deg[i])]
        lines.append(",".join(fields + ([f"{camp.temp_c[i]:.3f}"] if temperature else [])))
    path.write_text("\n".join(lines) + "\n")


def test_twin_predict_and_compensate_take_temp_c(warm_model, tmp_path, capsys):
    """``twin predict`` reads an optional ``temp_c`` column and predicts there; without
    it, one warning line says the terms are at their reference temperature. ``twin
    compensate`` solves joints whose prediction at the target's temperature is the target."""
    path, data = warm_model
    model = load_robot(str(path))
    camp = data.campaign
    rows = np.flatnonzero(camp.mask("validate"))[:8]
    for temperature in (True, False):
        joints, out = tmp_path / f"j{temperature}.csv", tmp_path / f"p{temperature}.csv"
        _joints_csv(joints, camp, rows, temperature)
        args = ["predict", "--model", str(path), "--data", str(joints), "--out", str(out)]
        assert main(args) == 0
        err = capsys.readouterr().err
        assert ("reference temperature" in err) is not temperature, err
        got = np.loadtxt(out, delimiter=",", skiprows=1, usecols=(1, 2, 3))
        temp = camp.temp_c[rows] if temperature else None
        want = predict_tcp(model, camp.q_rad[rows], camp.t_s[rows], temp_c=temp)
        np.testing.assert_allclose(got, want, atol=2e-4)
    targets = tmp_path / "targets.csv"
    goal = data.true_prediction_mm[rows]
    lines = ["target,x_mm,y_mm,z_mm," + ",".join(f"q{j}_deg" for j in range(1, 7)) + ",temp_c"]
    for k, i in enumerate(rows):
        fields = [f"T{k}", *(f"{v:.6f}" for v in goal[k]), *(f"{v:.6f}" for v in camp.q_deg[i])]
        lines.append(",".join([*fields, f"{camp.temp_c[i]:.3f}"]))
    targets.write_text("\n".join(lines) + "\n")
    solved = tmp_path / "solved.csv"
    assert (
        main(["compensate", "--model", str(path), "--targets", str(targets), "--out", str(solved)])
        == 0
    )
    assert "reference temperature" not in capsys.readouterr().err
    q = np.loadtxt(solved, delimiter=",", skiprows=1, usecols=range(1, 7))
    temp = np.round(camp.temp_c[rows], 3)
    reached = predict_tcp(model, np.radians(q), temp_c=temp)
    assert np.max(np.linalg.norm(reached - goal, axis=1)) < 1e-3


def test_tracked_checks_hold_the_expansion_at_their_temperature(warm_model, tmp_path):
    """``twin track``'s effect terms are the model's prediction at each check's
    temperature minus its geometry's (``temp_c`` of checks.csv), and the column is read."""
    from calibration.identify.campaign_files import read_checks
    from calibration.twin.tracking import effect_offsets

    path, data = warm_model
    model = load_robot(str(path))
    camp = data.campaign
    rows = np.flatnonzero(camp.mask("validate"))[:6]
    checks_csv = tmp_path / "checks.csv"
    write_campaign(checks_csv, camp.subset(np.isin(np.arange(len(camp)), rows)))
    checks = read_checks(checks_csv, 6)
    np.testing.assert_allclose(checks.temp_c, camp.temp_c[rows], atol=1e-4)
    q = np.radians(checks.q_deg)
    held = effect_offsets(model, q, checks.t_s, checks.temp_c)
    geometry = tcp_positions(KinematicModel.from_description(model), q)
    want = predict_tcp(model, q, checks.t_s, temp_c=checks.temp_c) - geometry
    np.testing.assert_allclose(held, want, atol=1e-12)
    assert np.max(np.abs(held - effect_offsets(model, q, checks.t_s))) > 1e-3  # not at T_ref


def test_twin_track_on_the_emulated_production_run_uses_its_temperature(
    warm_model, tmp_path, capsys
):
    """The emulator's production checks after a warming campaign carry the arm's
    temperature; ``twin track`` on them predicts nearer the checks with the column than
    with it dropped (its static one-step error, from stdout), and says so when dropped."""
    from sim_devices.pose_campaign import CheckProgram, emulated_checks

    path, data = warm_model
    run = emulated_checks(data, 2, CheckProgram(hours=2.0), THERMAL)
    assert run.checks.temp_c is not None and np.ptp(run.checks.temp_c) > 0.5
    static = {}
    for temperature in (True, False):
        checks = run.checks if temperature else replace(run.checks, temp_c=None)
        csv_path = tmp_path / f"checks{temperature}.csv"
        write_campaign(csv_path, checks)
        out = tmp_path / f"tracked{temperature}.csv"
        assert (
            main(["track", "--model", str(path), "--data", str(csv_path), "--out", str(out)]) == 0
        )
        captured = capsys.readouterr()
        line = next(x for x in captured.out.splitlines() if x.startswith("one-step-ahead"))
        static[temperature] = float(line.split("static ")[1].split(" mm")[0])
        assert ("reference temperature" in captured.err) is not temperature
    assert static[True] < 0.8 * static[False], static


def test_bad_temp_c_in_joints_and_targets_is_one_line(warm_model, tmp_path, capsys):
    """A kelvin value in joints.csv's or targets.csv's ``temp_c``: one line naming the
    file, the line and the column; exit 2, nothing written."""
    path, data = warm_model
    camp = data.campaign
    joints = tmp_path / "joints.csv"
    _joints_csv(joints, camp, [0, 1, 2], True)
    lines = joints.read_text().splitlines()
    lines[2] = ",".join([*lines[2].split(",")[:-1], "296.2"])
    joints.write_text("\n".join(lines) + "\n")
    targets = tmp_path / "targets.csv"
    head = "target,x_mm,y_mm,z_mm," + ",".join(f"q{j}_deg" for j in range(1, 7)) + ",temp_c"
    row = ",".join(["T1", "1000", "0", "1500", *(f"{v:.4f}" for v in camp.q_deg[0]), "296.2"])
    targets.write_text(f"{head}\n{row}\n")
    for command, option, bad, line in (
        ("predict", "--data", joints, "line 3"),
        ("compensate", "--targets", targets, "line 2"),
    ):
        out = tmp_path / f"{command}.csv"
        assert main([command, "--model", str(path), option, str(bad), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(bad) in err[0] and line in err[0], err
        assert "column 'temp_c'" in err[0] and "kelvin" in err[0]
        assert not out.exists()
