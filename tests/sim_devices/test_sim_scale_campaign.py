"""Static scale campaign with the chain's motion, several reflectors and short arcs."""

from __future__ import annotations

import math
import tomllib
from functools import cache

import numpy as np
import pytest

from calibration.model.description import load_robot
from sim_devices import scale_campaign
from sim_devices.config import CellConfig
from sim_devices.effects import UndeclaredEffects
from sim_devices.plant import Plant
from sim_devices.scale_campaign import CampaignOptions, run_campaign
from sim_devices.sweep_plan import motion_direction, sweep_stops_deg, target_set_mm
from sim_devices.truth import COUNTER_MODULUS, TrueCell

PLAIN_HEADER = "joint,pass,step,counts,x_mm,y_mm,z_mm"


@cache
def cell(robot: str = "kr500", seed: int = 1) -> TrueCell:
    return TrueCell.create(load_robot(robot), seed, eccentricity_mm=0.002)


@cache
def campaign(**options) -> scale_campaign.ScaleCampaign:
    return run_campaign(cell(), CampaignOptions(**options))


def test_plain_file_unchanged_and_all_counts_only_adds_columns():
    plain = campaign()
    assert plain.sweep_csv().splitlines()[0] == PLAIN_HEADER
    wide = campaign(all_counts=True)
    rows, wide_rows = plain.sweep_csv().splitlines(), wide.sweep_csv().splitlines()
    assert wide_rows[0] == PLAIN_HEADER + "," + ",".join(f"g{i}_counts" for i in range(1, 7))
    assert [r.split(",")[:7] for r in wide_rows] == [r.split(",")[:7] for r in rows]
    g = wide.sweep_all_counts
    np.testing.assert_array_equal(g[np.arange(len(g)), wide.sweep_joint - 1], wide.sweep_counts)
    assert plain.home_csv() == wide.home_csv()
    # nothing moves: the joints held at Home read their Home counts within read noise
    m = wide.sweep_joint == 3
    strip = cell().strips[1]
    home2 = strip.ideal_counts(0.0) % COUNTER_MODULUS
    assert np.abs(g[m, 1] - home2).max() <= 3


def test_torsion_and_backlash_turn_the_joints_held_at_home_as_the_live_plant_does():
    camp = campaign(torsion=True, backlash=True)
    plain = campaign()
    # the same draws: the tracker noise of every point is the plain campaign's (its σ
    # follows the point's distance, which the torsion changes by tenths of a mm)
    np.testing.assert_allclose(
        camp.sweep_points_mm - camp.sweep_true_points_mm,
        plain.sweep_points_mm - plain.sweep_true_points_mm,
        rtol=1e-3,
        atol=1e-5,
    )
    assert camp.sweep_csv().splitlines()[0].endswith("g6_counts")
    arcsec = np.degrees(camp.upstream_motion_rad(3)) * 3600
    assert 20.0 < arcsec[1] < 60.0  # joint 2 during joint 3's sweep
    # the gratings of the joints held at Home read their rings
    m = camp.sweep_joint == 3
    strip = cell().strips[1]
    ideal = strip.ideal_counts(camp.sweep_ring_rad[m, 1])
    offset = np.mod(camp.sweep_all_counts[m, 1] - ideal + 2**31, 2**32) - 2**31
    assert np.abs(offset).max() < 3
    assert np.ptp(camp.sweep_all_counts[m, 1]) > math.radians(20 / 3600) * strip.radius_mm * 1e3
    # the live plant's gears give the same motion over the same program (±1″)
    plant = Plant.from_config(CellConfig.loads("[cell]\nseed = 1\n"))
    sched = plant.trajectory.schedule()
    t = np.array(
        [
            0.5 * (s["arrive_s"] + s["leave_s"])
            for s in sched
            if s["label"].startswith("joint3 sweep")
        ]
    )
    st = plant.joint_state(t)
    live = np.degrees(np.ptp(st.q_out_rad - st.q_cmd_rad, axis=0)) * 3600
    assert abs(live[1] - arcsec[1]) < 1.0


def test_home_ring_is_where_the_twins_zero_refers_to():
    camp = campaign(torsion=True, backlash=True, settling_deg=0.002)
    for joint in (2, 3):
        truth = camp.truth(joint)
        rings = camp.home_ring_rad[camp.home_joint == joint, joint - 1]
        assert truth.home_ring_rad == pytest.approx(float(rings.mean()), abs=1e-15)
        assert abs(truth.home_ring_rad - truth.home_rad) > math.radians(2 / 3600)  # torsion
        counts = camp.home_counts[camp.home_joint == joint]
        # the mean Home reading is angle 0 from the ring's Home, not from the commanded one
        zero = np.degrees(np.mean(rings) - truth.home_rad)
        mean_angle = np.mean(truth.angle_deg(counts))
        assert abs(mean_angle - zero) < 2e-5
        assert abs(np.mean(truth.angle_from_home_ring_deg(counts))) < 2e-5
    doc = camp.truth_document()
    rows = {r["joint"]: r for r in doc["joint_truth"]}
    assert rows[3]["home_ring_deg"] == pytest.approx(math.degrees(camp.truth(3).home_ring_rad))
    assert len(rows[3]["upstream_motion_arcsec"]) == 2


def test_gravity_deflection_moves_the_target_and_no_grating():
    base = campaign(torsion=True, backlash=True)
    soft = campaign(
        torsion=True, backlash=True, effects=UndeclaredEffects.named("gravity_deflection")
    )
    np.testing.assert_array_equal(soft.sweep_all_counts, base.sweep_all_counts)
    np.testing.assert_array_equal(soft.sweep_ring_rad, base.sweep_ring_rad)
    moved = np.linalg.norm(soft.sweep_true_points_mm - base.sweep_true_points_mm, axis=1)
    m1 = soft.sweep_joint == 1
    assert moved[m1].max() < 1e-9  # joint 1 about the vertical: rigid
    assert 0.01 < moved[soft.sweep_joint == 3].max() < 1.0
    doc = soft.truth_document()["campaign"]["effects"]
    assert doc["gravity_deflection"] and doc["derived_stiffness_nmm_per_rad"][0] == 0.0


def test_three_reflectors_on_a_short_arc():
    camp = campaign(targets=3, arc_deg=30.0, stops_per_arc=10, joints=(2, 4))
    lines = camp.sweep_csv().splitlines()
    assert lines[0] == "joint,pass,step,target,counts,x_mm,y_mm,z_mm"
    assert len(lines) - 1 == 2 * 2 * 10 * 3
    assert [ln.split(",")[3] for ln in lines[1:4]] == ["1", "2", "3"]
    assert len({ln.split(",")[4] for ln in lines[1:4]}) == 1  # one stop, one reading
    pts = camp.sweep_true_points_mm.reshape(-1, 3, 3)
    sides = np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2)
    np.testing.assert_allclose(sides, 360.0, atol=1e-9)
    assert np.abs(camp.sweep_points_mm - camp.sweep_true_points_mm).max() < 0.1
    # centred on Home: commanded ±15°, forward and backward over the same stops
    q = np.degrees(camp.sweep_true_rad[(camp.sweep_joint == 2) & (camp.sweep_target == 1)])
    assert abs(q.max() - 15.0) < 0.05 and abs(q.min() + 15.0) < 0.05
    # the reflectors' plane does not contain the axis (they sit at different heights)
    local = camp.targets_mm[0]
    assert np.ptp(local[:, 2]) > 100.0
    with pytest.raises(ValueError, match="at least one"):
        target_set_mm((100.0, 0.0, 0.0), 0)


def test_arcs_stay_inside_the_limits():
    stops = sweep_stops_deg(-40.0, 110.0, 0.0, arc_deg=470.0, stops_per_arc=10)
    assert (stops[0], stops[-1]) == (110.0, -40.0)  # longer than the range: limit to limit
    stops = sweep_stops_deg(-350.0, 350.0, 0.0, arc_deg=470.0, stops_per_arc=10)
    assert (stops[0], stops[-1]) == (235.0, -235.0)
    stops = sweep_stops_deg(-120.0, 65.0, 60.0, arc_deg=40.0, stops_per_arc=5)
    assert (stops[0], stops[-1]) == (65.0, 25.0)  # Home near a limit: shifted inside
    np.testing.assert_array_equal(sweep_stops_deg(-10.0, 10.0, 0.0, step_deg=2.0)[:2], [10, 8])
    np.testing.assert_array_equal(
        motion_direction([10.0, 8.0, 8.0, 9.0], start=0.0, last_direction=-1.0), [1, -1, -1, 1]
    )
    np.testing.assert_array_equal(motion_direction([0.0, 0.0], 0.0, -1.0), [-1, -1])


def test_time_dependent_effects_follow_the_campaign_clock():
    lag = UndeclaredEffects.named("thermal_lag", lag_joint=2)
    camp = run_campaign(cell(), CampaignOptions(joints=(3,), effects=lag))
    plain = run_campaign(cell(), CampaignOptions(joints=(3,)))
    growth = 0.15 * (1.0 - np.exp(-camp.sweep_t_s / 900.0))
    moved = np.linalg.norm(camp.sweep_true_points_mm - plain.sweep_true_points_mm, axis=1)
    np.testing.assert_allclose(moved, growth, atol=1e-9)  # a2 upstream of link 3: a length
    assert camp.home_t_s[-1] < camp.sweep_t_s[0]


def test_command_line_flags(tmp_path):
    out = tmp_path / "run"
    args = ["--robot", "hp20d", "--seed", "2", "--out", str(out), "--joints", "2,3"]
    args += ["--torsion", "--backlash", "--effect", "gravity_deflection", "--targets", "3"]
    rc = scale_campaign.main([*args, "--arc-deg", "40", "--stops-per-arc", "8"])
    assert rc == 0
    header = (out / "sweep.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["joint", "pass", "step", "target"] and header[-1] == "g6_counts"
    doc = tomllib.loads((out / "truth.toml").read_text())
    assert doc["campaign"]["torsion"] and doc["campaign"]["targets"] == 3
    assert doc["gears"]["stiffness_nmm_per_rad"][1] == 4e10
    assert "counterbalance" not in doc["physical_arm"]
    assert scale_campaign.main(["--out", str(tmp_path / "w"), "--all-counts", "--joints", "1"]) == 0
    assert (tmp_path / "w" / "sweep.csv").read_text().startswith(PLAIN_HEADER + ",g1_counts")
