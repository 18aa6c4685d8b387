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
