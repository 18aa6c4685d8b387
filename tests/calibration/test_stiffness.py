"""Process force and stiffness: C = J K⁻¹ Jᵀ, a load test that finds K, and compensation
that takes a tool force's deflection out, proven on the emulated cell.

The emulator deflects its joints after the grating rings by its own compliance (the one
its gravity deflection uses, :func:`sim_devices.effects.force_stiffness_nmm_per_rad`);
the twin gets the campaign and a load test's tracker readings, never that stiffness. The
stiffnesses the load test finds are checked against the emulator's, and the compensated
commands under a force against the twin's own held-out prediction error.
"""

from __future__ import annotations

import csv
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel, geometric_jacobian, tcp_positions
from calibration.model.stiffness import (
    StiffnessError,
    cartesian_compliance,
    fit_joint_compliance,
    force_deflection_mm,
)
from calibration.twin.compensation import compensate
from sim_devices.effects import UndeclaredEffects, force_stiffness_nmm_per_rad, true_tcp_mm
from sim_devices.pose_campaign import sample_reachable_poses
from sim_devices.program import calibrated_cell, force_compensation_trial, load_test
from tests.calibration.test_bad_input_twin import refused, twin

STIFF = (3.7e10, 2.9e10, 5.4e9, 1.1e9, 1.8e9, 1.5e9)  # N·mm/rad, a KR500-like arm


def with_stiffness(desc, k=STIFF):
    joints = tuple(replace(j, stiffness_nmm_per_rad=v) for j, v in zip(desc.joints, k, strict=True))
    return replace(desc, joints=joints)


def mean_ap(errors) -> float:
    return float(np.mean(np.linalg.norm(errors, axis=1)))


def test_compliance_is_j_kinv_jt_and_matches_the_deflected_kinematics():
    desc = with_stiffness(load_robot("kr500"))
    model = KinematicModel.from_description(desc)
    q = sample_reachable_poses(desc, 30, np.random.default_rng(0))
    c = cartesian_compliance(desc, q)
    np.testing.assert_allclose(c, np.swapaxes(c, 1, 2), rtol=0, atol=1e-18)
    assert np.all(np.linalg.eigvalsh(c[:, :3, :3]) > -1e-15)
    f = np.random.default_rng(1).normal(0, 500.0, (30, 3))
    # the joints turned by K⁻¹·Jᵀ·F, through the exact kinematics: linear to first order
    jp = geometric_jacobian(model, q, point="tcp", frame="world")[:, :3, :]
    dq = np.einsum("min,mi->mn", jp, f) / np.array(STIFF)
    exact = tcp_positions(model, q + dq) - tcp_positions(model, q)
    linear = force_deflection_mm(desc, q, f)
    assert np.max(np.linalg.norm(exact - linear, axis=1)) < 1e-3 * np.max(np.abs(linear))


def test_the_emulators_force_deflection_is_what_the_twins_formula_gives_its_stiffness():
    """The same physics on both sides (sign, frame, point of action): the emulator's TCP
    under a force minus without it equals C·F with the emulator's own stiffnesses."""
    desc = load_robot("hp20d")
    settings = UndeclaredEffects.named("gravity_deflection")
    k = force_stiffness_nmm_per_rad(settings, desc)
    q = sample_reachable_poses(desc, 20, np.random.default_rng(2))
    f = np.random.default_rng(3).normal(0, 300.0, (20, 3))
    t = np.zeros(20)
    moved = true_tcp_mm(settings, desc, q, t, None, f) - true_tcp_mm(settings, desc, q, t)
    twin_view = force_deflection_mm(with_stiffness(desc, tuple(k)), q, f)
    assert np.max(np.abs(moved)) > 0.05  # a force the tracker sees
    np.testing.assert_allclose(moved, twin_view, atol=2e-3 * np.max(np.abs(moved)))


def test_load_test_fit_recovers_compliances_and_flags_unexcited_joints():
    desc = with_stiffness(load_robot("kr500"))
    q = sample_reachable_poses(desc, 10, np.random.default_rng(4))
    qq = np.repeat(q, 6, axis=0)
    f = 800.0 * np.tile(np.vstack([np.eye(3), -np.eye(3)]), (10, 1))
    fit = fit_joint_compliance(load_robot("kr500"), qq, f, force_deflection_mm(desc, qq, f))
    assert fit.determined.all()
    np.testing.assert_allclose(fit.stiffness_nmm_per_rad, STIFF, rtol=1e-6)
    # a tool point on axis 6: a force there puts no torque on joint 6
    on_axis = replace(desc, tool=replace(desc.tool, x_mm=0.0, y_mm=0.0))
    d = force_deflection_mm(on_axis, qq, f)
    fit = fit_joint_compliance(replace(on_axis, joints=load_robot("kr500").joints), qq, f, d)
    assert fit.excited.tolist() == [True] * 5 + [False]
    np.testing.assert_allclose(fit.stiffness_nmm_per_rad[:5], STIFF[:5], rtol=1e-6)
    applied = fit.applied_to(load_robot("kr500"))
    assert applied.joints[5].stiffness_nmm_per_rad is None
    assert applied.joints[4].stiffness_nmm_per_rad == pytest.approx(STIFF[4], rel=1e-6)
    with pytest.raises(StiffnessError, match="excites no joint"):
        fit_joint_compliance(desc, qq, 0 * f, 0 * f)


def test_a_force_without_stiffness_is_refused():
    desc = load_robot("kr500")
    q = np.degrees(sample_reachable_poses(desc, 3, np.random.default_rng(5)))
    p = tcp_positions(KinematicModel.from_description(desc), np.radians(q))
    with pytest.raises(StiffnessError, match="stiffness"):
        compensate(desc, p, q_programmed_deg=q, force_n=np.ones((3, 3)))
    res = compensate(desc, p, q_programmed_deg=q, force_n=np.zeros((3, 3)))
    assert res.ok.all() and np.allclose(res.force_deflection_mm, 0)


@pytest.mark.parametrize(("robot", "seed"), [("kr500", 1), ("hp20d", 2)])
def test_force_compensation_realises_the_twins_prediction(robot, seed):
    trial = force_compensation_trial(robot, seed, force_n=1000.0, n_targets=100)
    assert trial.refused == 0
    before = mean_ap(trial.before_mm)
    plain, after = mean_ap(trial.after_no_force_mm), mean_ap(trial.after_mm)
    twin_error = mean_ap(trial.twin_validation_mm)
    print(f"{robot} seed {seed}: before {before:.4f}, without force compensation "
          f"{plain:.4f}, with {after:.4f} mm; twin's held-out {twin_error:.4f} mm")  # fmt: skip
    assert plain > 4 * after  # the force matters, and its compensation takes it out
    assert after <= 1.2 * twin_error
    # the load test's stiffnesses against the emulator's own (never given to the twin)
    fit, truth = trial.fit, trial.true_stiffness_nmm_per_rad
    ok = fit.determined
    assert ok[:5].all()  # a 29 mm tool offset hardly loads joint 6: it may stay open
    rel_se = fit.std_error[ok] / fit.compliance[ok]
    error = np.abs(truth[ok] / fit.stiffness_nmm_per_rad[ok] - 1.0)  # in compliance
    assert np.all(error <= 3 * rel_se + 0.02), (error, rel_se)


# -- the commands ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def stiffness_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("stiff")
    cell = calibrated_cell("kr500", 7, ("gravity_deflection",), 20)
    cell.calibrated.save(root / "cal.toml")
    test = load_test(cell.data, cell.calibrated, 8, 1000.0, cell.rng, 1e5)
    # the unloaded readings are the loaded minus the measured deflection (one reading each)
    loaded = tcp_positions(KinematicModel.from_description(cell.calibrated), np.radians(test.q_deg))
    unloaded = loaded - test.deflection_mm
    head = ["load", *(f"q{i}_deg" for i in range(1, 7)), "fx_n", "fy_n", "fz_n"]
    head += ["x0_mm", "y0_mm", "z0_mm", "x_mm", "y_mm", "z_mm"]
    with open(root / "loads.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for i in range(len(test.q_deg)):
            w.writerow([f"L{i}", *(f"{v:.9f}" for v in test.q_deg[i]),
                        *(f"{v:g}" for v in test.force_n[i]),
                        *(f"{v:.6f}" for v in unloaded[i]),
                        *(f"{v:.6f}" for v in loaded[i])])  # fmt: skip
    force = np.tile([0.0, 0.0, -1000.0], (20, 1))
    with open(root / "targets.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["target", "x_mm", "y_mm", "z_mm", *(f"q{i}_deg" for i in range(1, 7)),
                    "fx_n", "fy_n", "fz_n"])  # fmt: skip
        for i in range(20):
            w.writerow([f"T{i}", *(f"{v:.6f}" for v in cell.target_mm[i]),
                        *(f"{v:.9f}" for v in cell.q_programmed_deg[i]), *force[i]])  # fmt: skip
    return root, cell, force


def test_twin_stiffness_load_test_writes_the_model_with_stiffnesses(stiffness_files, tmp_path):
    root, cell, _ = stiffness_files
    proc = twin(root, "stiffness", "--model", "cal.toml", "--load-test", "loads.csv",
                "--out-model", str(tmp_path / "stiff.toml"))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "48 loads" in proc.stdout, proc.stdout
    doc = tomllib.loads((tmp_path / "stiff.toml").read_text())
    k = [j.get("stiffness_nmm_per_rad") for j in doc["joint"]]
    truth = force_stiffness_nmm_per_rad(cell.data.effects, cell.data.cell.arm)
    assert None not in k[:5]
    np.testing.assert_allclose(k[:5], truth[:5], rtol=0.25)


def test_twin_stiffness_reports_compliance_along_a_feed(stiffness_files, tmp_path):
    cell = stiffness_files[1]
    stiff = with_stiffness(cell.calibrated)
    stiff.save(tmp_path / "stiff.toml")
    with open(tmp_path / "poses.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["pose", *(f"q{i}_deg" for i in range(1, 7))])
        for i, q in enumerate(cell.q_programmed_deg[:10]):
            w.writerow([f"P{i}", *(f"{v:.9f}" for v in q)])
    proc = twin(tmp_path, "stiffness", "--model", "stiff.toml", "--data", "poses.csv",
                "--feed", "1,0,0", "--out", "c.csv")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "stiffest poses" in proc.stdout
    with open(tmp_path / "c.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    c = cartesian_compliance(stiff, np.radians(cell.q_programmed_deg[:10]))[:, :3, :3] * 1e3
    got = np.array([float(r["feed_um_per_n"]) for r in rows])
    np.testing.assert_allclose(got, c[:, 0, 0], rtol=1e-5)
    softest = np.array([float(r["softest_um_per_n"]) for r in rows])
    np.testing.assert_allclose(softest, np.linalg.eigvalsh(c)[:, -1], rtol=1e-5)
    assert np.all(softest >= got - 1e-9)


def test_twin_compensate_takes_a_tool_force_out(stiffness_files, tmp_path):
    root, cell, force = stiffness_files
    stiff = with_stiffness(cell.calibrated)
    stiff.save(tmp_path / "stiff.toml")
    (tmp_path / "targets.csv").write_bytes((root / "targets.csv").read_bytes())
    proc = twin(tmp_path, "compensate", "--model", "stiff.toml", "--targets", "targets.csv",
                "--out", "j.csv")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    with open(tmp_path / "j.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    q = np.radians([[float(r[f"q{i}_deg"]) for i in range(1, 7)] for r in rows])
    from calibration.effects.model_effects import predict_tcp

    reached = predict_tcp(stiff, q) + force_deflection_mm(stiff, q, force)
    assert np.max(np.linalg.norm(reached - cell.target_mm, axis=1)) < 1e-5
    deflection = np.array([float(r["force_deflection_mm"]) for r in rows])
    expected = np.linalg.norm(force_deflection_mm(stiff, q, force), axis=1)
    np.testing.assert_allclose(deflection, expected, rtol=1e-5)


@pytest.mark.parametrize(
    ("args", "keywords"),
    [
        (["compensate", "--model", "cal.toml", "--targets", "targets.csv", "--out", "j.csv"],
         ["targets.csv", "fx_n", "cal.toml", "stiffness"]),
        (["stiffness", "--model", "cal.toml", "--data", "targets.csv"],
         ["cal.toml", "stiffness_nmm_per_rad"]),
        (["stiffness", "--model", "cal.toml", "--load-test", "loads.csv", "--out", "x.csv"],
         ["--out", "--data"]),
        (["stiffness", "--model", "cal.toml", "--load-test", "loads.csv"], ["--out-model"]),
        (["stiffness", "--model", "cal.toml", "--load-test", "loads.csv", "--out-model",
          "loads.csv"], ["--out-model", "input"]),
        (["stiffness", "--model", "cal.toml", "--data", "targets.csv", "--feed", "0,0,0"],
         ["--feed", "non-zero"]),
        (["stiffness", "--model", "cal.toml", "--load-test", "noforce.csv", "--out-model",
          "m.toml"], ["noforce.csv", "fx_n"]),
        (["compensate", "--model", "cal.toml", "--targets", "onlyfx.csv", "--out", "j.csv"],
         ["onlyfx.csv", "fy_n"]),
        (["stiffness", "--model", "negk.toml", "--data", "targets.csv"],
         ["negk.toml", "stiffness_nmm_per_rad", "positive"]),
    ],
)  # fmt: skip
def test_stiffness_and_force_inputs_are_refused_clearly(stiffness_files, tmp_path, args, keywords):
    root = stiffness_files[0]
    for f in ("cal.toml", "targets.csv", "loads.csv"):
        (tmp_path / f).write_bytes((root / f).read_bytes())
    loads = (root / "loads.csv").read_text()
    (tmp_path / "noforce.csv").write_text(loads.replace("fx_n", "f_x", 1))
    targets = (root / "targets.csv").read_text()
    (tmp_path / "onlyfx.csv").write_text(targets.replace("fy_n", "fyy", 1))
    cal = (root / "cal.toml").read_text()
    (tmp_path / "negk.toml").write_text(
        cal.replace("[[joint]]\n", "[[joint]]\nstiffness_nmm_per_rad = -1.0\n", 1)
    )
    refused(tmp_path, args, *keywords)
