"""The live twin's check of its paired devices' host clocks (calibration/twin/live_clocks.py):
the replay's rule (10 ms beyond the uncertainties), read from the devices' health."""

from __future__ import annotations

import json

from calibration.twin.live_clocks import HEALTH_WAIT_S, PairedClocks
from calibration.twin.streams import HOST_CLOCK_TOLERANCE_MS, host_clocks_apart

G = "cell/cell1/robot/robot1/grating/health"
T = "cell/cell1/robot/robot1/tracker/health"


def _health(offset_ms: float, uncertainty_ms: float) -> bytes:
    clock = {"offset_ms": offset_ms, "uncertainty_ms": uncertainty_ms, "rtt_ms": 0.7}
    return json.dumps({"device": "x", "host_clock": clock}).encode()


def test_clocks_apart_say_so_once_and_agree_again() -> None:
    clocks = PairedClocks({"grating": G, "tracker": T, "encoders": "cell/c/e/health"})
    assert clocks.check() is None and clocks.doc()["agree"] is None  # nothing known yet
    clocks.take(G, _health(0.2, 0.1))
    assert clocks.check() is None and not clocks.apart  # one clock alone: not compared
    doc = clocks.doc()
    assert doc["devices"] == {
        "grating": {"kind": "grating", "offset_ms": 0.2, "uncertainty_ms": 0.1}
    }
    # the tracker's PC 500 ms ahead: said once, in one line naming both and the offsets
    clocks.take(T, _health(500.0, 0.35))
    line = clocks.check()
    assert line is not None and "\n" not in line
    assert "the grating (grating) and the tracker (tracker)" in line
    assert "499.8 ms apart" in line and "+0.2 ± 0.1" in line and "+500.0 ± 0.3" in line
    assert clocks.apart and clocks.check() is None
    doc = clocks.doc()
    assert doc["agree"] is False and doc["apart_ms"] == 499.8 and doc["times_apart"] == 1
    assert doc["tolerance_ms"] == HOST_CLOCK_TOLERANCE_MS
    # set right again
    clocks.take(T, _health(1.0, 0.3))
    line = clocks.check()
    assert line is not None and "agree again" in line and not clocks.apart
    assert clocks.doc()["agree"] is True


def test_the_rule_is_the_replays_within_the_uncertainties() -> None:
    clocks = PairedClocks({"grating": G, "tracker": T})
    # 11 ms apart, each ± 1 ms: within 10 ms beyond the uncertainties, paired
    clocks.take(G, _health(-5.5, 1.0))
    clocks.take(T, _health(5.5, 1.0))
    assert clocks.check() is None and not clocks.apart
    assert not host_clocks_apart((-5.5, 1.0), (5.5, 1.0))
    # 13 ms apart, each ± 1 ms: 11 beyond, refused as a replay refuses it
    clocks.take(T, _health(7.5, 1.0))
    assert clocks.check() is not None and clocks.apart
    assert host_clocks_apart((-5.5, 1.0), (7.5, 1.0))


def test_health_without_a_clock_or_of_another_device_is_not_compared() -> None:
    clocks = PairedClocks({"grating": G, "tracker": T})
    clocks.take(G, _health(0.0, 0.1))
    clocks.take(T, json.dumps({"device": "tracker"}).encode())  # no host_clock (zenohd)
    clocks.take(T, b"not json")
    clocks.take("cell/cell1/robot/robot1/other/health", _health(900.0, 0.1))
    assert clocks.check() is None and not clocks.apart
    assert set(clocks.doc()["devices"]) == {"grating"}


def test_tracker_samples_are_learned_only_from_clocks_known_to_agree() -> None:
    now = [0.0]
    clocks = PairedClocks({"grating": G, "tracker": T}, clock=lambda: now[0])
    assert not clocks.admits(5)  # no health yet: the clocks are not known
    clocks.take(G, _health(0.2, 0.1))
    assert not clocks.admits(5)  # the tracker's not yet
    clocks.take(T, json.dumps({"device": "tracker"}).encode())  # health without a clock
    assert clocks.check() is None and clocks.admits(5)  # both heard: not compared, as a replay
    clocks.take(T, _health(500.0, 0.3))
    assert clocks.check() is not None and not clocks.admits(7)
    assert clocks.doc()["tracker_samples_dropped"] == 17
    clocks.take(T, _health(0.5, 0.3))
    assert clocks.check() is not None and clocks.admits(1)
    # devices that publish no health are paired unchecked after HEALTH_WAIT_S
    quiet = PairedClocks({"grating": G, "tracker": T}, clock=lambda: now[0])
    assert not quiet.admits(1)
    now[0] = HEALTH_WAIT_S
    assert quiet.admits(1)
