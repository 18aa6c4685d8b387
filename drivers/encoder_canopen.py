"""Driver of the CiA 406 motor encoders on CANopen (the ``canopen`` master, python-can).

URL forms: ``socketcand://HOST:PORT/CHANNEL`` (a socketcand server, across processes;
client :class:`drivers.socketcand.SocketcandBus`) or ``virtual://CHANNEL`` (python-can's
in-process virtual bus). Options name the node ids. On connect the driver reads each
node's device type (0x1000 must be a CiA 406 encoder), resolution (0x6001/0x6002) and
TPDO1 COB-ID over SDO, sets the producer heartbeat time, starts the nodes (NMT) and
produces SYNC at ``sync_hz``. Each SYNC gives one sample row: the six position values
(0x6004, counts) from the TPDO1s.

Heartbeats are watched: a node silent for ``heartbeat_timeout_factor`` × its period is
counted in ``heartbeat_losses`` and its channel gets the ``node_lost`` status until it is
heard again; a node that reboots (boot-up / PRE-OPERATIONAL heartbeat) is restarted with
NMT and counted in ``node_restarts``.

Device clock: the CAN interface's frame timestamp (for socketcand, the server's), µs.

On socketcand one I/O thread does the cyclic work: at each SYNC instant (a fixed grid at
``sync_hz``; a late SYNC is sent at once, one per cycle, and the grid restarts when
more than ``max_sync_lag`` periods behind, counted in ``missed_syncs``) it takes every
frame that arrived, assembles rows from the TPDOs, watches heartbeats, hands anything
else to canopen (:meth:`canopen.Network.notify`) and sends the SYNC: one wake-up per
cycle instead of a notifier and a cyclic-send thread. On the virtual bus canopen's
notifier and SYNC producer are used.
"""

from __future__ import annotations

import binascii
import collections
import contextlib
import logging
import threading
import time
import urllib.parse
from typing import Any, ClassVar

import canopen
import numpy as np

from drivers.base import BatchSchema, ChannelSchema, DeviceClock, Driver, Option, SampleBatch
from drivers.cia406 import DEVICE_TYPE_CIA406_MULTITURN, object_dictionary
from drivers.errors import DeviceIOError, DriverConfigError
from drivers.socketcand import SocketcandBus, format_send
from edges.channel_names import ENCODER, counts_column

log = logging.getLogger(__name__)

ST_VALID = 0x0001
ST_MISSING = 0x0002  # no TPDO from this node in this SYNC cycle
ST_NODE_LOST = 0x0004  # heartbeat lost
STATUS_BITS = {ST_VALID: "valid", ST_MISSING: "missing_in_cycle", ST_NODE_LOST: "node_lost"}
SCHEMES = ("socketcand", "virtual")


def parse_can_url(url: str) -> dict[str, Any]:
    """``socketcand://host:port/channel`` or ``virtual://channel`` → python-can kwargs."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in SCHEMES:
        raise DriverConfigError(
            f"CAN URL must start with {' or '.join(s + '://' for s in SCHEMES)}, got {url!r}"
        )
    if parts.scheme == "virtual":
        channel = parts.netloc or parts.path.strip("/")
        if not channel:
            raise DriverConfigError(f"virtual://CHANNEL needs a channel name: {url!r}")
        return {"interface": "virtual", "channel": channel}
    if not parts.hostname or not parts.port or not parts.path.strip("/"):
        raise DriverConfigError(f"expected socketcand://HOST:PORT/CHANNEL, got {url!r}")
    return {
        "interface": "socketcand",
        "host": parts.hostname,
        "port": parts.port,
        "channel": parts.path.strip("/"),
    }


class EncoderCanopenDriver(Driver):
    """SYNC-driven reading of CiA 406 encoders; see the module docstring."""

    kind = "encoder_canopen"
    OPTIONS: ClassVar[dict[str, Option]] = {
        "node_ids": Option(tuple, (1, 2, 3, 4, 5, 6), "CANopen node ids, one per channel"),
        "sync_hz": Option(float, 1000.0, "SYNC rate produced by the driver"),
        "heartbeat_ms": Option(int, 100, "producer heartbeat time written to 0x1017"),
        "heartbeat_timeout_factor": Option(float, 3.0, "node lost after this many periods"),
        "sdo_timeout_s": Option(float, 0.5, "SDO response timeout"),
        "batch_rows": Option(int, 10, "return from read() once this many rows are in"),
        "max_sync_lag": Option(int, 20, "SYNC periods late before the grid restarts"),
        "quiet_python_can": Option(bool, True, "python-can's per-read warnings off"),
    }

    def __init__(self, url: str, **options: Any) -> None:
        if "node_ids" in options and isinstance(options["node_ids"], list):
            options["node_ids"] = tuple(options["node_ids"])
        self.can_kwargs = parse_can_url(url)
        super().__init__(url, **options)
        ids = self.options["node_ids"]
        if not ids or not all(isinstance(i, int) and 1 <= i <= 127 for i in ids):
            raise DriverConfigError(f"node_ids must be CANopen ids 1..127, got {ids!r}")
        self.node_ids: tuple[int, ...] = ids
        self.n = len(ids)
        self._schema = BatchSchema(
            kind=self.kind,
            channels=tuple(
                ChannelSchema(
                    counts_column(ENCODER, k + 1),
                    "count",
                    "int64",
                    f"node {nid} position value 0x6004 (motor counts, multi-turn)",
                )
                for k, nid in enumerate(ids)
            ),
            status_bits=STATUS_BITS,
            device_clock="CAN interface frame timestamp, µs",
            source="CANopen TPDO1 0x6004 on SYNC",
        )
        self.network: canopen.Network | None = None
        self._cond = threading.Condition()
        #: closed rows: sequence, device time s, host time ns, counts, status per node
        self._rows: collections.deque[tuple[int, float, int, list[int], list[int]]] = (
            collections.deque(maxlen=200_000)
        )
        self._cur = [0] * self.n
        self._filled = [False] * self.n
        self._n_filled = 0
        self._cur_t: float | None = None
        self._cur_host = 0
        self._cob_to_k: dict[int, int] = {}
        self._hb_last = [0.0] * self.n  # time.monotonic of the last heartbeat
        self._lost = [False] * self.n
        self._restart_pending: set[int] = set()
        self._booted: set[int] = set()
        self._seq = 0
        self._io: threading.Thread | None = None
        self._io_stop = threading.Event()
        self._io_error: BaseException | None = None
        self._sync_on = False
        self.clock = DeviceClock(bits=63, max_gap_us=3_600_000_000)
        self.counters.update({"heartbeat_losses": 0, "node_restarts": 0, "missed_syncs": 0})
        if self.options["quiet_python_can"]:
            lg = logging.getLogger("can.interfaces.socketcand.socketcand")
            if lg.level == logging.NOTSET:
                lg.setLevel(logging.ERROR)  # "incomplete message" on every split TCP read

    @property
    def schema(self) -> BatchSchema:
        return self._schema

    # -- link -----------------------------------------------------------------------------
    def _connect(self) -> None:
        kw = dict(self.can_kwargs)
        self._io_error = None
        self._sync_on = False
        if kw["interface"] == "socketcand":
            bus = SocketcandBus(kw["channel"], kw["host"], kw["port"])
            net = canopen.Network(bus)  # fed by our I/O thread (no python-can notifier)
            self.network = net
            self._io_stop.clear()
            self._io = threading.Thread(
                target=self._io_loop, args=(net, bus), name="encoder-canopen-io", daemon=True
            )
            self._io.start()
        else:
            net = canopen.Network()
            kw["receive_own_messages"] = False
            try:
                net.connect(**kw)
            except Exception as exc:
                raise DeviceIOError(f"cannot open CAN bus {self.url}: {exc}") from exc
            self.network = net
        try:
            self._configure(net)
        except Exception as exc:
            raise DeviceIOError(f"CANopen setup on {self.url} failed: {exc}") from exc
        if self._io is not None:
            self._sync_on = True
        else:
            net.sync.start(1.0 / self.options["sync_hz"])

    def _configure(self, net: canopen.Network) -> None:
        info = {}
        self._cob_to_k.clear()  # (the I/O thread holds this dict)
        for k, nid in enumerate(self.node_ids):
            node = canopen.RemoteNode(nid, object_dictionary(nid))
            net.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = self.options["sdo_timeout_s"]
            dev_type = node.sdo[0x1000].raw
            if dev_type & 0xFFFF != DEVICE_TYPE_CIA406_MULTITURN & 0xFFFF:
                raise DeviceIOError(f"node {nid}: device type {dev_type:#x} is not CiA 406")
            cpr = node.sdo[0x6001].raw
            total = node.sdo[0x6002].raw
            cob = node.sdo[0x1800][1].raw & 0x7FF
            node.sdo[0x1017].raw = self.options["heartbeat_ms"]
            info[nid] = {
                "device_type": dev_type,
                "counts_per_rev": cpr,
                "total_range": total,
                "tpdo1_cob_id": cob,
            }
            self._cob_to_k[cob] = k
            net.subscribe(cob, self._on_tpdo)
            net.subscribe(0x700 + nid, self._on_heartbeat)
        self.info["nodes"] = info
        # the heartbeat watch starts now: setting up six nodes over SDO can take longer
        # than a heartbeat timeout on a busy machine
        self._hb_last = [time.monotonic()] * self.n
        self._lost = [False] * self.n
        net.nmt.send_command(0x01)  # start all nodes (broadcast)

    def _disconnect(self) -> None:
        net, self.network = self.network, None
        io, self._io = self._io, None
        self._sync_on = False
        if io is not None:
            self._io_stop.set()
            io.join(2.0)
        if net is None:
            return
        with contextlib.suppress(Exception):
            net.sync.stop()
        with contextlib.suppress(Exception):
            net.disconnect()

    # -- the socketcand I/O thread ------------------------------------------------------------
    def _io_loop(self, net: canopen.Network, bus: SocketcandBus) -> None:
        period = 1.0 / self.options["sync_hz"]
        max_lag = self.options["max_sync_lag"] * period
        sync = format_send(0x080, b"")
        tpdo = self._cob_to_k
        hb_lo, hb_hi = 0x701, 0x77F
        unhex = binascii.unhexlify
        due: float | None = None
        try:
            while not self._io_stop.is_set():
                if not self._sync_on:
                    raw = bus.poll_raw(0.01)  # setup: SDO answers as they come
                    due = None
                else:
                    now = time.monotonic()
                    if due is None:
                        due = now
                    elif due > now:
                        time.sleep(due - now)
                    elif now - due > max_lag:
                        missed = int((now - due) / period)
                        self.count("missed_syncs", missed, "SYNC grid restarted")
                        due = now
                    raw = bus.poll_raw()
                values: list[tuple[int, bytes, bytes]] = []
                for ident, ts, data in raw:
                    if len(ident) > 3:
                        continue  # extended frame: not CANopen
                    can_id = int(ident, 16)
                    k = tpdo.get(can_id)
                    if k is not None:
                        values.append((k, data, ts))
                        continue
                    try:
                        payload = unhex(data)
                    except (ValueError, binascii.Error):
                        self.count("protocol_errors", detail=f"odd hex data in frame {can_id:03X}")
                        continue
                    if hb_lo <= can_id <= hb_hi:
                        self._on_heartbeat(can_id, payload, float(ts))
                    else:
                        net.notify(can_id, bytearray(payload), float(ts))
                if values:
                    self._on_tpdos(values)
                if bus.garbage_bytes:
                    self.count("garbage_bytes", bus.garbage_bytes)
                    bus.garbage_bytes = 0
                if self._sync_on and due is not None:
                    bus.send_raw(sync)
                    due += period
        except Exception as exc:  # the link is gone: read() reconnects
            self._io_error = exc
            with self._cond:
                self._cond.notify_all()

    # -- callbacks (the I/O thread, or canopen's notifier on the virtual bus) ---------------
    def _on_tpdo(self, can_id: int, data: bytes | bytearray, timestamp: float) -> None:
        k = self._cob_to_k.get(can_id)
        if k is None or len(data) < 4:
            return
        value = int.from_bytes(data[:4], "little")
        with self._cond:
            filled = self._filled
            if filled[k]:
                self._close_row()
            if self._cur_t is None:
                self._cur_t = timestamp
                self._cur_host = time.monotonic_ns()
            self._cur[k] = value
            filled[k] = True
            self._n_filled += 1
            if all(f or lost for f, lost in zip(filled, self._lost, strict=True)):
                self._close_row()

    def _on_tpdos(self, values: list[tuple[int, bytes, bytes]]) -> None:
        """TPDOs of one I/O cycle, as ``(channel, data_hex, seconds)`` (the I/O thread)."""
        unhex = binascii.unhexlify
        n = self.n
        with self._cond:
            filled, cur, lost = self._filled, self._cur, self._lost
            any_lost = any(lost)
            for k, data, ts in values:
                try:
                    raw = unhex(data)
                except (ValueError, binascii.Error):
                    self.count("protocol_errors", detail="odd hex data in a TPDO")
                    continue
                if len(raw) < 4:
                    continue
                if filled[k]:
                    self._close_row()
                if self._cur_t is None:
                    self._cur_t = float(ts)
                    self._cur_host = time.monotonic_ns()
                cur[k] = int.from_bytes(raw[:4], "little")
                filled[k] = True
                self._n_filled += 1
                if self._n_filled == n or (
                    any_lost and all(f or x for f, x in zip(filled, lost, strict=True))
                ):
                    self._close_row()

    def _close_row(self) -> None:
        lost = self._lost
        status = [
            (ST_VALID if f else ST_MISSING) | (ST_NODE_LOST if lost[k] else 0)
            for k, f in enumerate(self._filled)
        ]
        self._rows.append((self._seq, self._cur_t or 0.0, self._cur_host, list(self._cur), status))
        self._seq += 1
        self._filled[:] = [False] * self.n  # in place: _on_tpdo holds this list
        self._n_filled = 0
        self._cur_t = None
        if len(self._rows) >= self.options["batch_rows"]:
            self._cond.notify()

    def _on_heartbeat(self, can_id: int, data: bytes | bytearray, timestamp: float) -> None:
        nid = can_id - 0x700
        if nid not in self.node_ids or not data:
            return
        k = self.node_ids.index(nid)
        self._hb_last[k] = time.monotonic()
        state = data[0] & 0x7F
        if state == 0x00:  # boot-up message: the node rebooted
            self._booted.add(nid)
        if state in (0x00, 0x7F):  # boot-up or PRE-OPERATIONAL: (re)start it
            self._restart_pending.add(nid)
        if self._lost[k]:
            self._lost[k] = False

    # -- reading --------------------------------------------------------------------------
    def _watch(self) -> None:
        net = self.network
        if net is None:
            return
        limit = self.options["heartbeat_ms"] / 1000.0 * self.options["heartbeat_timeout_factor"]
        now = time.monotonic()
        for k, nid in enumerate(self.node_ids):
            if not self._lost[k] and now - self._hb_last[k] > limit:
                self._lost[k] = True
                self.count("heartbeat_losses", detail=f"node {nid}")
        while self._restart_pending:
            nid = self._restart_pending.pop()
            try:
                net.send_message(0x000, bytes([0x01, nid]))
            except Exception as exc:
                raise DeviceIOError(f"NMT start failed: {exc}") from exc
        while self._booted:
            self.count("node_restarts", detail=f"node {self._booted.pop()}")

    def _link_error(self) -> str | None:
        if self._io_error is not None:
            return f"CAN link failed: {self._io_error}"
        net = self.network
        notifier = None if net is None else net.notifier
        if notifier is not None and getattr(notifier, "exception", None) is not None:
            return f"CAN receive failed: {notifier.exception}"
        return None

    def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
        net = self.network
        if net is None or net.bus is None:
            raise DeviceIOError("not connected")
        if (err := self._link_error()) is not None:
            raise DeviceIOError(err)
        self._watch()
        with self._cond:
            while len(self._rows) < self.options["batch_rows"]:
                left = (deadline_ns - time.monotonic_ns()) / 1e9
                if left <= 0:
                    break
                self._cond.wait(min(left, 0.05))
                if (err := self._link_error()) is not None:
                    raise DeviceIOError(err)
            rows = list(self._rows)
            self._rows.clear()
        if not rows:
            return None
        n = len(rows)
        seq = np.fromiter((r[0] for r in rows), np.uint64, n)
        t_raw = np.fromiter((round(r[1] * 1e6) for r in rows), np.int64, n)
        host = np.fromiter((r[2] for r in rows), np.int64, n)
        values = np.array([r[3] for r in rows], np.int64)
        status = np.array([r[4] for r in rows], np.uint16)
        before = self.clock.restarts
        t_us, epoch = self.clock.unwrap(t_raw)
        if self.clock.restarts != before:
            self.count("device_restarts", self.clock.restarts - before, "CAN clock went back")
        return SampleBatch(self._schema, seq, t_us, epoch, host, values, status)
