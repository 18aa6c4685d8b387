"""The host clocks of the devices the live twin pairs by time (docs/deployment.md, "Clocks").

A daemon that is a client of a router measures its host's clock against the router's and
says it in each device's health (``host_clock``: ``offset_ms``, ``uncertainty_ms``). The
live twin pairs the tracker's samples with the gratings' by their mapped times to learn
its tracking updates (:mod:`calibration.twin.live_tracking`); stamped by two hosts whose
clocks disagree, a pair would be off by the clocks' difference. :class:`PairedClocks`
keeps each device's latest ``host_clock`` and judges the pair by the rule a replay
refuses with (:func:`~calibration.twin.streams.host_clocks_apart`, 10 ms beyond the
uncertainties). While they disagree the twin feeds the tracker's samples to nobody (no
update is learned from them) and counts them; it keeps publishing its state (the
gratings' alone). So it does too until both devices' health has come once (a period,
1 s by default; at most :data:`HEALTH_WAIT_S`): a pair is learned from only once its
clocks are known. Devices whose health has no ``host_clock`` (loopback, ``zenohd``) are
not compared, as in a replay.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

from calibration.twin.streams import HOST_CLOCK_TOLERANCE_MS, host_clock_of, host_clocks_apart

#: the kinds of stream whose clocks are compared (the pair a tracking update is made of)
PAIRED_KINDS = ("grating", "tracker")
#: the longest the tracker's samples wait for the devices' first health documents (s):
#: beyond, devices that publish none are paired unchecked
HEALTH_WAIT_S = 3.0


class PairedClocks:
    """The latest ``host_clock`` of the grating's and the tracker's devices, by their health
    keys (``health_keys``: kind -> key; the tracker absent when not tracking).

    :meth:`take` is called with each health document (any thread); :meth:`check` judges
    the pair and returns a line to say when the verdict changed; ``apart`` is the verdict
    (False while either clock is unknown); :meth:`admits` says whether tracker samples may
    be learned from now. ``clock``: monotonic seconds (tests give their own)."""

    def __init__(
        self, health_keys: Mapping[str, str], clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.keys = {k: v for k, v in health_keys.items() if k in PAIRED_KINDS}
        self._kind_of = {v: k for k, v in self.keys.items()}
        self._clock = clock
        self._since = clock()
        self.heard: frozenset[str] = frozenset()  # kinds whose health has come
        self.latest: dict[str, dict[str, float]] = {}
        self.apart = False
        self.times_apart = 0  # times the pair went apart
        self.tracker_samples_dropped = 0  # tracker samples not learned from (clocks apart)

    def take(self, key: str, data: bytes) -> None:
        """A health document ``data`` of ``key``: keep its ``host_clock`` (if any)."""
        kind = self._kind_of.get(key)
        if kind is not None and kind not in self.heard:
            self.heard = self.heard | {kind}  # one assignment: read by another thread
        clock = host_clock_of(data) if kind is not None else None
        if kind is not None and clock is not None:
            self.latest = {**self.latest, kind: clock}  # one assignment: read by another thread

    def admits(self, n: int) -> bool:
        """Whether ``n`` tracker samples may be learned from: not while the clocks are
        apart, nor before both devices' health came (at most :data:`HEALTH_WAIT_S`);
        those not admitted are counted."""
        known = self.heard >= set(self.keys) or self._clock() - self._since >= HEALTH_WAIT_S
        if known and not self.apart:
            return True
        self.tracker_samples_dropped += n
        return False

    def _device(self, kind: str) -> str:
        return self.keys[kind].rsplit("/", 2)[-2]

    def _apart_ms(self) -> float | None:
        g, t = self.latest.get("grating"), self.latest.get("tracker")
        if g is None or t is None:
            return None
        return abs(g["offset_ms"] - t["offset_ms"])

    def check(self) -> str | None:
        """Judge the pair again; the line to say (stderr) when the verdict changed, None
        when it did not."""
        latest = self.latest
        g, t = latest.get("grating"), latest.get("tracker")
        apart = (
            g is not None
            and t is not None
            and host_clocks_apart(
                (g["offset_ms"], g["uncertainty_ms"]), (t["offset_ms"], t["uncertainty_ms"])
            )
        )
        if apart == self.apart:
            return None
        self.apart = apart
        assert g is not None and t is not None  # a verdict changes only with both known
        gap = abs(g["offset_ms"] - t["offset_ms"])
        grating, tracker = self._device("grating"), self._device("tracker")
        names = f"the grating ({grating}) and the tracker ({tracker})"
        if apart:
            self.times_apart += 1
            return (
                f"{names} are stamped by host clocks {gap:.1f} ms apart (host_clock in their "
                f"health: {g['offset_ms']:+.1f} ± {g['uncertainty_ms']:.1f} and "
                f"{t['offset_ms']:+.1f} ± {t['uncertainty_ms']:.1f} ms against the router's; "
                f"tolerance {HOST_CLOCK_TOLERANCE_MS:.0f} ms): no tracking update is learned "
                "from their samples until they agree; set the hosts' clocks (NTP/PTP)"
            )
        return f"{names} agree again ({gap:.1f} ms apart): tracking updates are learned again"

    def doc(self) -> dict[str, Any]:
        """The twin's health document's ``clocks`` (docs/topics.md, "Twin keys")."""
        gap = self._apart_ms()
        return {
            "devices": {
                self._device(kind): {"kind": kind, **self.latest[kind]}
                for kind in self.keys
                if kind in self.latest
            },
            "apart_ms": None if gap is None else round(gap, 3),
            "tolerance_ms": HOST_CLOCK_TOLERANCE_MS,
            "agree": None if gap is None else not self.apart,
            "times_apart": self.times_apart,
            "tracker_samples_dropped": self.tracker_samples_dropped,
        }
