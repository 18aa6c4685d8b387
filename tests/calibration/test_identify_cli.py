"""``twin identify`` and ``twin predict`` as a user runs them (subprocesses)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from calibration.cli import main
from calibration.effects.identification_report import COMPONENTS, REPORT_FILES, STATISTICS
from calibration.effects.model_effects import ModelEffectError, predict_tcp
from calibration.identify import identifiability, identification
from calibration.identify.campaign_files import read_campaign, read_points, write_campaign
from calibration.identify.levenberg_marquardt import LMSettings
from calibration.model.description import EffectDescription, load_robot
from sim_devices import pose_campaign
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign


def twin(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "calibration.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cli")
    data = emulated_campaign("kr500", 21, CampaignSettings(n_identify=60, n_validate=40))
    path = tmp / "campaign.csv"
    write_campaign(path, data.campaign)
    return tmp, path, data


@pytest.fixture(scope="module")
def identified(campaign):
    tmp, path, _ = campaign
    out = tmp / "calibrated.toml"
    rep = tmp / "report"
    proc = twin("identify", "--robot", "kr500", "--data", str(path), "--out", str(out),
                "--report", str(rep), "--tracker-mpe-um", "15,6")  # fmt: skip
    return proc, out, rep


def test_identify_writes_model_and_report(campaign, identified):
    _, _, data = campaign
    proc, out, rep = identified
    assert proc.returncode == 0, proc.stderr
    assert "LM iteration" in proc.stderr  # progress
    assert "validate: mean AP" in proc.stdout
    for name in REPORT_FILES:
        assert (rep / name).stat().st_size > 0, name
    doc = json.loads((rep / "report.json").read_text())
    for set_name in ("identify", "validate"):
        s = doc["sets"][set_name]
        for when in ("before", "after"):
            for comp in COMPONENTS:
                assert set(s[when][comp]) == set(STATISTICS)
        assert s["improvement"]["AP"]["mean"]["ratio"] > 10.0
    assert doc["data"]["skipped_rows"] == 0
    # weighted by the data sheet: the residual noise matches the stated one
    assert 0.7 < doc["noise_sigma_mm"] / doc["reference_sigma_mm"] < 1.3
    assert doc["solver"]["point_weights"].startswith("tracker MPE")
    assert doc["identifiability"]["n_identified"] == 27
    assert "joint3.d_mm" in [d["name"] for d in doc["identifiability"]["dropped"]]
    assert doc["identifiability"]["condition_number"] > 1.0
    params = {p["name"]: p for p in doc["parameters"]}
    assert params["joint2.a_mm"]["standard_error"] > 0
    assert params["joint2.alpha_deg"]["unit"] == "deg"
    assert params["joint1.d_mm"]["standard_error"] is None
    enc = doc["encoder_minus_grating_deg"]
    assert len(enc) == 6 and all(0.0 < e["max_abs"] < 0.05 for e in enc)
    md = (rep / "report.md").read_text()
    assert "| AP after |" in md and "Dropped parameters" in md

    # the calibrated description keeps name, limits and masses, and any command reads it
    calibrated = load_robot(out)
    nominal = load_robot("kr500")
    assert calibrated.name == nominal.name
    for a, b in zip(calibrated.joints, nominal.joints, strict=True):
        assert (a.lower_deg, a.upper_deg, a.mass_kg) == (b.lower_deg, b.upper_deg, b.mass_kg)
    vm = data.campaign.mask("validate")
    pred = predict_tcp(calibrated, data.campaign.q_rad[vm])
    after = np.linalg.norm(pred - data.campaign.xyz_mm[vm], axis=1).mean()
    true = np.linalg.norm(data.tcp_true_mm[vm] - data.campaign.xyz_mm[vm], axis=1).mean()
    assert after < 1.2 * true


def test_predict(campaign, identified):
    tmp, path, data = campaign
    _, model, _ = identified
    joints = tmp / "joints.csv"
    # a campaign file is a valid joints file: extra columns are ignored
    points = tmp / "points.csv"
    proc = twin("predict", "--model", str(model), "--data", str(path), "--out", str(points))
    assert proc.returncode == 0, proc.stderr
    poses, xyz = read_points(points)
    assert poses == data.campaign.pose
    err = np.linalg.norm(xyz - data.tcp_true_mm, axis=1)
    assert err.max() < 0.1
    # bad row in joints.csv: named, or skipped and counted
    lines = path.read_text().splitlines()
    fields = lines[3].split(",")
    fields[5] = "999"  # q3 out of limits
    lines[3] = ",".join(fields)
    joints.write_text("\n".join(lines) + "\n")
    proc = twin("predict", "--model", str(model), "--data", str(joints), "--out", str(points))
    assert proc.returncode == 2
    assert "line 4" in proc.stderr and "q3_deg" in proc.stderr
    proc = twin("predict", "--model", str(model), "--data", str(joints), "--out", str(points),
                "--skip-bad")  # fmt: skip
    assert proc.returncode == 0 and "skipped 1 bad row" in proc.stderr
    assert len(read_points(points)[0]) == len(data.campaign) - 1


def test_identify_bad_rows_named_or_counted(campaign, tmp_path, capsys):
    _, path, _ = campaign
    lines = path.read_text().splitlines()
    lines[5] = lines[5].replace(",identify,", ",identify,nan,", 1).rsplit(",", 1)[0]
    lines.append(lines[2])  # duplicated pose id
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "cal.toml"
    rc = main(["identify", "--robot", "kr500", "--data", str(bad), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "line 6" in err and "t_s" in err
    rep = tmp_path / "rep"
    rc = main(["identify", "--robot", "kr500", "--data", str(bad), "--out", str(out),
               "--quiet", "--skip-bad", "--report", str(rep)])  # fmt: skip
    assert rc == 0
    assert "skipped 2 bad row(s)" in capsys.readouterr().out
    doc = json.loads((rep / "report.json").read_text())
    assert doc["data"]["skipped_rows"] == 2
    reasons = " ".join(s["reason"] for s in doc["data"]["skipped"])
    assert "duplicated pose id" in reasons
    assert len(read_campaign(bad, 6, skip_bad=True)) == len(lines) - 1 - 2


def test_missing_column_and_no_identify_rows(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("pose,set,t_s,q1_deg\n1,identify,0,0\n")
    rc = main(["identify", "--robot", "kr500", "--data", str(bad), "--out", "x.toml"])
    assert rc == 2 and "missing column" in capsys.readouterr().err
    header = "pose,set,t_s," + ",".join(f"q{i}_deg" for i in range(1, 7)) + ",x_mm,y_mm,z_mm"
    bad.write_text(header + "\n1,validate,0,0,0,0,0,30,0,1,2,3\n")
    rc = main(["identify", "--robot", "kr500", "--data", str(bad), "--out", "x.toml"])
    assert rc == 2 and "no rows with set 'identify'" in capsys.readouterr().err


def test_unknown_effect_kind_is_a_clear_error(tmp_path, capsys):
    desc = load_robot("kr500")
    with_effect = replace(desc, effects=(EffectDescription("joint_compliance", {"k": 1.0}),))
    with pytest.raises(ModelEffectError, match="joint_compliance"):
        predict_tcp(with_effect, np.zeros((1, 6)))
    model = tmp_path / "m.toml"
    with_effect.save(model)
    joints = tmp_path / "j.csv"
    joints.write_text(
        "pose,t_s," + ",".join(f"q{i}_deg" for i in range(1, 7)) + "\n1,0,0,0,0,0,30,0\n"
    )
    rc = main(
        ["predict", "--model", str(model), "--data", str(joints), "--out", str(tmp_path / "p.csv")]
    )
    assert rc == 2 and "unknown effect kind 'joint_compliance'" in capsys.readouterr().err


def test_predict_holds_a_drift_at_the_campaign_span_and_says_so(tmp_path, capsys):
    """A linear drift identified over [0, 3600] s: rows at 7200 s get the drift's value at
    3600 s, and a warning says how many rows were outside; rows inside: no warning."""
    drift = EffectDescription(
        "length_drift",
        {"joint": 2.0, "a_rate_mm_per_h": 0.2, "t0_s": 0.0, "t_min_s": 0.0, "t_max_s": 3600.0},
    )
    model = tmp_path / "m.toml"
    replace(load_robot("kr500"), effects=(drift,)).save(model)
    rows = ["pose,t_s," + ",".join(f"q{i}_deg" for i in range(1, 7))]
    rows += [f"{k},{t},10,20,-30,40,50,60" for k, t in enumerate((1800, 3600, 7200, 9000))]
    joints = tmp_path / "j.csv"
    joints.write_text("\n".join(rows) + "\n")
    points = tmp_path / "p.csv"
    rc = main(["predict", "--model", str(model), "--data", str(joints), "--out", str(points)])
    err = capsys.readouterr().err
    assert rc == 0 and "2 row(s) outside the campaign's time span [0, 3600] s" in err
    _, xyz = read_points(points)
    np.testing.assert_allclose(xyz[2], xyz[1], atol=1e-9)  # held, not extrapolated
    np.testing.assert_allclose(xyz[3], xyz[1], atol=1e-9)
    assert np.linalg.norm(xyz[1] - xyz[0]) > 0.05  # within the span it drifts (0.1 mm)
    joints.write_text("\n".join(rows[:3]) + "\n")
    main(["predict", "--model", str(model), "--data", str(joints), "--out", str(points)])
    assert "outside" not in capsys.readouterr().err


def test_twin_robot_checks_effect_tables_as_predict_does(tmp_path, capsys):
    """`twin robot` rejects exactly what `twin predict` rejects, naming the table and key."""
    bad = EffectDescription("joint_harmonic", {"joint": 1.0, "order": 2.0, "sin_deg": 0.0})
    path = tmp_path / "m.toml"
    replace(load_robot("kr500"), effects=(bad,)).save(path)
    assert main(["robot", str(path)]) == 2
    err = capsys.readouterr().err
    assert "[[effect]] #1" in err and "cos_deg" in err
    good = EffectDescription(
        "joint_harmonic", {"joint": 1.0, "order": 2.0, "sin_deg": 0.0, "cos_deg": 0.001}
    )
    replace(load_robot("kr500"), effects=(good,)).save(path)
    assert main(["robot", str(path)]) == 0
    assert "effects: cyclic error of joint 1 (harmonic 2)" in capsys.readouterr().out


def test_campaign_generator_command(tmp_path):
    out = tmp_path / "campaign.csv"
    truth = tmp_path / "truth.toml"
    args = ["--robot", "hp20d", "--seed", "3", "--out", str(out), "--truth", str(truth)]
    rc = pose_campaign.main([*args, "--identify", "30", "--validate", "10"])
    assert rc == 0 and truth.exists()
    camp = read_campaign(
        out, 6, limits_deg=[(j.lower_deg, j.upper_deg) for j in load_robot("hp20d").joints]
    )
    assert len(camp) == 40 and camp.mask("identify").sum() == 30
    assert np.all(np.diff(camp.t_s) > 0) and camp.encoder_deg is not None
    assert len(set(camp.pose)) == 40


def test_identify_without_base_guess_registers(campaign, tmp_path, capsys):
    _, path, data = campaign
    robot = tmp_path / "robot.toml"
    replace(load_robot("kr500"), base=None).save(robot)
    out = tmp_path / "cal.toml"
    rc = main(["identify", "--robot", str(robot), "--data", str(path), "--out", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "base start: registration" in captured.err
    calibrated = load_robot(out)
    assert calibrated.base is not None
    # the base absorbs joint 1's deviations (dropped: held nominal), a few 0.1 mm and 0.01°
    truth_base = data.cell.truth.base
    assert abs(calibrated.base.x_mm - truth_base.x_mm) < 2.0
    assert abs(calibrated.base.rz_deg - truth_base.rz_deg) < 0.1


# -- the closed loop through the command line --------------------------------------------------
def test_clean_campaign_runs_the_loop_and_adds_nothing(identified):
    proc, out, rep = identified
    assert "closed loop: nothing significant left" in proc.stderr
    assert "stage geometric calibration: validate mean AP" in proc.stdout
    doc = json.loads((rep / "report.json").read_text())
    loop = doc["closed_loop"]
    assert [s["stage"] for s in loop["stages"]] == ["nominal", "geometric"]
    assert loop["added"] == [] and loop["stopped"]["best_remaining"]["p_adjusted"] > 1e-3
    assert "tracker scale" in [c["effect"] for c in loop["stopped"]["not_identifiable"]]
    assert load_robot(out).effects == ()
    md = (rep / "report.md").read_text()
    assert "## Closed loop" in md and "| geometric calibration |" in md


def test_loop_names_the_effect_and_predict_applies_it(tmp_path):
    """An undeclared gravity deflection: named, written into calibrated.toml, reported with
    evidence, and `twin predict` reproduces the loop's validation errors from the file."""
    camp = tmp_path / "campaign.csv"
    rc = pose_campaign.main(
        [
            "--robot",
            "hp20d",
            "--seed",
            "7",
            "--out",
            str(camp),
            "--identify",
            "80",
            "--validate",
            "60",
            "--effect",
            "gravity_deflection",
        ]
    )
    assert rc == 0
    out, rep = tmp_path / "cal.toml", tmp_path / "rep"
    proc = twin("identify", "--robot", "hp20d", "--data", str(camp), "--out", str(out),
                "--report", str(rep))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "closed loop: added gravity deflection" in proc.stderr
    cal = load_robot(out)
    assert [e.kind for e in cal.effects] == ["gravity_deflection"]
    assert 'form = "physical"' in out.read_text() and "compliance_ratio" in out.read_text()
    doc = json.loads((rep / "report.json").read_text())
    loop = doc["closed_loop"]
    assert (loop["cross_validation"], loop["cross_validation_score"]) == (
        "leave one pose out",
        "predictive deviance",
    )
    assert (
        "leave one pose out, each scored by its predictive deviance"
        in (rep / "report.md").read_text()
    )
    stages = loop["stages"]
    assert [s["stage"] for s in stages] == ["nominal", "geometric", "effect"]
    for st in stages:
        for comp in COMPONENTS:
            assert {"max", "min", "mean", "std"} <= set(st["sets"]["validate"][comp])
    eff = stages[2]["effect"]
    assert eff["kind"] == "gravity_deflection" and not eff["generic"]
    # joint 2's once-per-revolution harmonic spans link 2's own gravity columns: named as
    # the competitor the data cannot tell apart, left by physical priority (whether the
    # gravity term also scored higher, 180.2 against 179.7 σ² here, or not)
    look_alike = [
        c for c in eff["competitors"] if c["effect"].startswith("cyclic error of joint 2")
    ]
    assert look_alike and "cannot be told apart" in look_alike[0]["separated_by"]
    assert "physical priority" in look_alike[0]["separated_by"]
    assert eff["shape"]["gravity_form"]["kept"] == "physical"
    determined = [p for p in eff["parameters"] if p["standard_error"] is not None]
    assert len(determined) >= 8 and all(p["standard_error"] > 0 for p in determined)
    assert (rep / eff["evidence_plot"]).stat().st_size > 0
    ap = [s["sets"]["validate"]["AP"]["mean"] for s in stages]
    assert ap[0] > ap[1] > 2 * ap[2]
    assert doc["sets"]["validate"]["after"]["AP"]["mean"] == pytest.approx(ap[2])
    md = (rep / "report.md").read_text()
    assert "### Stages" in md and "3. Added gravity deflection" in md
    assert md.count("| + gravity deflection") == 4  # one row per component table
    assert "Why this effect: " in md and "Compliance ratios" in md
    assert look_alike[0]["separated_by"] in md  # the competitors' table
    # predict applies the effect: its points give the loop's validation errors
    points = tmp_path / "points.csv"
    proc = twin("predict", "--model", str(out), "--data", str(camp), "--out", str(points))
    assert proc.returncode == 0, proc.stderr
    _, xyz = read_points(points)
    c = read_campaign(camp, 6)
    vm = c.mask("validate")
    ap_predict = np.linalg.norm(c.xyz_mm[vm] - xyz[vm], axis=1).mean()
    assert ap_predict == pytest.approx(ap[2], rel=1e-4)  # points.csv holds 1 nm
    # --no-effects: the geometry alone, no [[effect]] tables, no closed-loop section
    out2, rep2 = tmp_path / "geo.toml", tmp_path / "rep2"
    rc = main(["identify", "--robot", "hp20d", "--data", str(camp), "--out", str(out2),
               "--report", str(rep2), "--no-effects", "--quiet"])  # fmt: skip
    assert rc == 0 and load_robot(out2).effects == ()
    doc2 = json.loads((rep2 / "report.json").read_text())
    assert "closed_loop" not in doc2
    assert doc2["sets"]["validate"]["after"]["AP"]["mean"] == pytest.approx(ap[1], rel=1e-9)


def test_effect_options_are_checked(campaign, tmp_path, capsys):
    _, path, _ = campaign
    out = tmp_path / "x.toml"
    rc = main(["identify", "--robot", "kr500", "--data", str(path), "--out", str(out),
               "--quiet", "--effect-kinds", "joint_harmonic,sag"])  # fmt: skip
    assert rc == 2 and "unknown effect kind 'sag'" in capsys.readouterr().err
    rc = main(["identify", "--robot", "kr500", "--data", str(path), "--out", str(out),
               "--quiet", "--effects-alpha", "2"])  # fmt: skip
    assert rc == 2 and "--effects-alpha" in capsys.readouterr().err
    rc = main(["identify", "--robot", "kr500", "--data", str(path), "--out", str(out),
               "--quiet", "--effect-kinds", "lost_motion"])  # fmt: skip
    assert rc == 0


# -- parameters without effect, and failed fits (issue 17) -------------------------------------
def _strict_json(text: str) -> dict:
    def no_constant(name: str) -> None:
        raise ValueError(f"report.json holds {name}")

    return json.loads(text, parse_constant=no_constant)


@pytest.fixture(scope="module")
def on_axis_campaign(tmp_path_factory):
    """A description with the tool on axis 6 (x = y = 0) and a campaign on a cell drawn
    around it."""
    tmp = tmp_path_factory.mktemp("on_axis")
    desc = load_robot("kr500")
    desc = replace(desc, tool=replace(desc.tool, x_mm=0.0, y_mm=0.0))
    robot = tmp / "robot.toml"
    desc.save(robot)
    data = emulated_campaign(desc, 1, CampaignSettings(n_validate=60))
    path = tmp / "campaign.csv"
    write_campaign(path, data.campaign)
    return robot, path, data


def test_tool_on_the_last_axis_through_the_cli(on_axis_campaign, tmp_path, capsys):
    robot, path, data = on_axis_campaign
    out, rep = tmp_path / "cal.toml", tmp_path / "rep"
    rc = main(["identify", "--robot", str(robot), "--data", str(path), "--out", str(out),
               "--report", str(rep), "--no-effects"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "dropped joint6.theta_offset_rad: no effect on the measured positions" in err
    doc = _strict_json((rep / "report.json").read_text())
    dropped = {d["name"]: d["reason"] for d in doc["identifiability"]["dropped"]}
    assert dropped["joint6.theta_offset_rad"] == "no effect on the measured positions"
    for p in doc["parameters"]:
        assert (p["standard_error"] is not None) == p["identified_from_data"], p["name"]
    vm = data.campaign.mask("validate")
    pred = predict_tcp(load_robot(out), data.campaign.q_rad[vm])
    after = np.linalg.norm(pred - data.campaign.xyz_mm[vm], axis=1).mean()
    true = np.linalg.norm(data.true_prediction_mm[vm] - data.campaign.xyz_mm[vm], axis=1).mean()
    assert after <= 1.1 * true


def _never_converging(monkeypatch) -> str:
    """The LM stopped after one iteration, far from converged."""
    real = identification.levenberg_marquardt

    def one_iteration(*args, **kwargs):
        return real(*args, **{**kwargs, "settings": LMSettings(max_iterations=1)})

    monkeypatch.setattr(identification, "levenberg_marquardt", one_iteration)
    return "the geometric fit did not converge: the maximum number of iterations was reached"


def _running_away(monkeypatch) -> str:
    """θ6 kept at the start point (no start-point test) runs away; no restart allowed."""
    monkeypatch.setattr(identifiability, "NO_EFFECT_TOL", 0.0)
    monkeypatch.setattr(identification, "MAX_RESTARTS", 0)
    return "joint6.theta_offset_rad ran away during the iterations"


@pytest.mark.parametrize("failure", [_never_converging, _running_away])
def test_a_failed_fit_writes_nothing_and_exits_2(
    failure, on_axis_campaign, tmp_path, capsys, monkeypatch
):
    robot, path, _ = on_axis_campaign
    reason = failure(monkeypatch)
    out, rep = tmp_path / "cal.toml", tmp_path / "rep"
    rc = main(["identify", "--robot", str(robot), "--data", str(path), "--out", str(out),
               "--report", str(rep), "--quiet"])  # fmt: skip
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert rc == 2
    assert len(lines) == 1 and lines[0].startswith("twin identify: error: "), captured.err
    assert reason in lines[0]
    assert not out.exists() and not rep.exists()
    assert "wrote" not in captured.out
