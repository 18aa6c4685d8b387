"""The public API of ``calibration``: its documented example runs as written, every name
in ``__all__`` resolves, and the solvers load only when used."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap

import calibration
from calibration.campaign_files import write_campaign
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign


def test_every_public_name_resolves():
    for name in calibration.__all__:
        assert getattr(calibration, name) is not None, name


def test_the_package_example_calibrates_a_campaign(tmp_path):
    data = emulated_campaign("kr500", 4, CampaignSettings(n_identify=60, n_validate=30))
    write_campaign(tmp_path / "campaign.csv", data.campaign)
    doc = calibration.__doc__ or ""
    code = textwrap.dedent(re.search(r"::\n\n((?:    .*\n|\n)+)", doc).group(1))
    assert code.count("\n") <= 6  # five lines of Python, as promised
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(code, "calibration.__doc__", "exec"), {})  # our own docstring
    finally:
        os.chdir(cwd)
    desc = calibration.load_robot(str(tmp_path / "calibrated.toml"))
    assert desc.base is not None and desc.n_joints == 6


def test_importing_the_package_does_not_load_the_solvers():
    code = "import sys, calibration; print('calibration.closed_loop' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "False", out.stderr
