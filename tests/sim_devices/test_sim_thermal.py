"""The emulator's thermal expansion with a temperature: the arm's temperature history, the
``temp_c`` column it writes, and the truth's growth following that temperature."""

from __future__ import annotations

import tomllib

import numpy as np

from calibration.identify.campaign_files import read_campaign
from calibration.model.kinematics import tcp_positions
from sim_devices import pose_campaign
from sim_devices.effects import UndeclaredEffects, arm_temperature_c
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign

SMALL = dict(n_identify=30, n_validate=20, selection=None)


def test_expansion_follows_the_written_temperature():
    """Same draws as the clean campaign; ``temp_c`` is the arm's temperature plus the
    sensor's noise; every true point moves as the true model with each link length
    grown by κ·(T − T_ref), computed here independently, pose by pose."""
    clean = emulated_campaign("kr500", 4, CampaignSettings(**SMALL))
    eff = UndeclaredEffects.named("thermal_expansion")
    data = emulated_campaign("kr500", 4, CampaignSettings(**SMALL, effects=eff))
    camp = data.campaign
    np.testing.assert_array_equal(camp.q_deg, clean.campaign.q_deg)
    np.testing.assert_array_equal(camp.t_s, clean.campaign.t_s)
    assert clean.campaign.temp_c is None and camp.temp_c is not None
    true_t = arm_temperature_c(eff, camp.t_s)
    noise = camp.temp_c - true_t
    assert 0.03 < float(np.std(noise)) < 0.08 and abs(float(np.mean(noise))) < 0.03
    assert float(np.ptp(true_t)) > 0.5  # 50 poses: the first ~12 min of the warm-up
    model = data.cell.model
    for i in range(0, len(camp), 7):
        grow = 1.0 + 1e-6 * eff.expansion_ppm_per_k * (true_t[i] - eff.temp_ref_c)
        x = model.parameter_vector()
        x[0 : 5 * model.n_joints : 5] *= grow
        x[2 : 5 * model.n_joints : 5] *= grow
        expected = tcp_positions(model.with_parameters(x), data.q_true_rad[i : i + 1])[0]
        np.testing.assert_allclose(data.tcp_true_mm[i], expected, atol=1e-9)
    shift = np.linalg.norm(data.tcp_true_mm - clean.tcp_true_mm, axis=1)
    assert 0.02 < float(shift.max()) < 0.3  # tens of µm: 1-2 K over 20 °C, a 3 m steel arm


def test_generator_writes_temp_c_and_the_truth(tmp_path):
    out, truth = tmp_path / "c.csv", tmp_path / "truth.toml"
    args = ["--robot", "hp20d", "--seed", "2", "--identify", "20", "--validate", "5"]
    rc = pose_campaign.main(
        [*args, "--out", str(out), "--truth", str(truth), "--effect", "thermal_expansion"]
    )
    assert rc == 0
    assert out.read_text().splitlines()[0].endswith(",temp_c")
    back = read_campaign(out, 6)
    assert back.temp_c is not None and 20.0 < float(back.temp_c.min()) < 25.0
    doc = tomllib.loads(truth.read_text())["undeclared_effects"]
    assert doc["thermal_expansion"] and doc["expansion_ppm_per_k"] == 11.5
    rc = pose_campaign.main([*args, "--out", str(out)])
    assert rc == 0 and "temp_c" not in out.read_text().splitlines()[0]


def test_a_campaign_measured_at_given_times_has_the_same_draws():
    """``measure_campaign(..., t_s)``: the poses at the times given, every random draw as
    without them, so the readings are the same; the truth at those times (a drift grown
    by its rate times the time given)."""
    nominal = emulated_campaign("kr500", 5, CampaignSettings(**SMALL))
    cell, q = nominal.cell, nominal.q_true_rad
    eff = UndeclaredEffects.named("thermal_drift")
    settings = CampaignSettings(**SMALL, effects=eff)
    timed = pose_campaign.measure_campaign(cell, q[:0], q, np.random.default_rng(2), settings)
    t = np.sort(np.random.default_rng(3).uniform(0.0, 600.0, len(q)))
    given = pose_campaign.measure_campaign(cell, q[:0], q, np.random.default_rng(2), settings, t)
    np.testing.assert_array_equal(given.campaign.t_s, t)
    np.testing.assert_array_equal(given.campaign.q_deg, timed.campaign.q_deg)
    np.testing.assert_array_equal(given.campaign.encoder_deg, timed.campaign.encoder_deg)
    at_zero = pose_campaign.measure_campaign(
        cell, q[:0], q, np.random.default_rng(2), settings, np.zeros(len(q))
    )
    grown = np.linalg.norm(given.tcp_true_mm - at_zero.tcp_true_mm, axis=1)
    assert np.all(np.diff(grown[np.argsort(t)]) > -1e-9)  # the drift only grows
    assert 0.5 * eff.drift_mm_per_h * 600 / 3600 < grown.max() < 2 * eff.drift_mm_per_h * 600 / 3600
