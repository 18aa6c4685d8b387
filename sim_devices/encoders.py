"""Emulated motor encoders: CANopen CiA 406 slaves built on the ``canopen`` package.

Each node is a :class:`canopen.LocalNode` (SDO server, NMT slave with heartbeat) loaded
with the profile's EDS (:mod:`drivers.cia406`). canopen's LocalNode does not transmit
TPDOs on SYNC by itself, so :class:`EncoderNodes` answers SYNC: for every node in
OPERATIONAL whose TPDO1 is valid and synchronous (transmission type 1..240, every n-th
SYNC), it sends the position value 0x6004 (u32, little endian) on the TPDO1 COB-ID.

The answer to a SYNC is :meth:`EncoderNodes.sync_frames`: on the in-process bus it is
sent through canopen (subscription to 0x080); the socketcand server calls it directly
for a SYNC from a TCP client (the emulated bus's fast path: no trip through python-can's
virtual bus and canopen's notifier thread per SYNC). Motor angles come from the plant
evaluated ahead on a 0.25 ms grid in blocks of 0.1 s (one vectorized call per block)
and interpolated linearly at the SYNC's instant (error < 0.1 count at the arm's top
speed and acceleration); an SDO read of 0x6004 evaluates the plant exactly.

Position value: ``round(motor_angle / 2π · counts_per_rev) + zero`` modulo the total
measuring range ``counts_per_rev · turns`` (multi-turn, wraps like a real encoder).
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import threading
from collections import Counter
from collections.abc import Callable

import can
import canopen
import numpy as np

from drivers.cia406 import POSITION_INDEX, TPDO1_COMM, TPDO1_MAP, object_dictionary
from sim_devices.config import EncoderSection
from sim_devices.plant import DeviceClock, Plant

log = logging.getLogger(__name__)

SYNC_COB_ID = 0x080
_U32 = struct.Struct("<I")


def _node_id(node: canopen.LocalNode) -> int:
    """A local node's id (canopen types it optional; ours are always given one)."""
    assert node.id is not None
    return int(node.id)


class EncoderNodes:
    """All encoder nodes of the robot on one python-can bus channel."""

    def __init__(
        self,
        plant: Plant,
        config: EncoderSection,
        *,
        interface: str = "virtual",
        channel: str = "simcell",
    ) -> None:
        self.plant = plant
        self.config = config
        self.channel = channel
        self.node_ids = tuple(config.node_ids[: plant.n_joints])
        self.range = config.counts_per_rev * config.turns
        rng = np.random.default_rng(plant.cell.seed + 31)
        self.zero_counts = rng.integers(0, self.range, len(self.node_ids))
        self.clock = DeviceClock(ppm=config.clock_ppm)
        self.stats: Counter[str] = Counter()
        self.network = canopen.Network()
        self.network.connect(interface=interface, channel=channel, receive_own_messages=False)
        self.nodes: list[canopen.LocalNode] = []
        self._tpdo: dict[int, tuple[int, int] | None] = {}
        self._sync_count = 0
        self._muted: set[int] = set()
        self._lock = threading.Lock()
        self._zeros = [int(z) for z in self.zero_counts]
        self._grid: tuple[int, list[list[float]]] = (0, [])
        for k, nid in enumerate(self.node_ids):
            od = object_dictionary(nid, config.counts_per_rev, config.turns)
            node = canopen.LocalNode(nid, od)
            self.network.add_node(node)
            node.sdo[0x1017].raw = config.heartbeat_ms  # type: ignore[union-attr]
            node.sdo[0x1018][4].raw = 0x406000 + nid  # type: ignore[index]
            node.add_read_callback(self._make_read_cb(k))
            node.add_write_callback(self._make_write_cb(nid))
            self.nodes.append(node)
            self._refresh_tpdo(node)
        self.network.subscribe(SYNC_COB_ID, self._on_sync)
        for node in self.nodes:
            self._boot(node)
        self._fault_thread: threading.Thread | None = None
        self._stop = threading.Event()

    # -- node behaviour -------------------------------------------------------------------
    def _boot(self, node: canopen.LocalNode) -> None:
        node.nmt.send_command(0x81)  # reset node: INITIALISING, boot-up message
        node.nmt.send_command(0x80)  # to PRE-OPERATIONAL: heartbeat starts

    def _make_read_cb(self, k: int) -> Callable[..., int | None]:
        def cb(index: int, subindex: int, od: object) -> int | None:
            if index == POSITION_INDEX:
                return int(self.positions(self.plant.clock.wall_s())[k])
            return None

        return cb

    def _make_write_cb(self, nid: int) -> Callable[..., None]:
        def cb(index: int, subindex: int, od: object, data: bytes) -> None:
            if index in (TPDO1_COMM, TPDO1_MAP):
                # applied after canopen stores the value: defer one tick
                threading.Timer(0.0, self._refresh_tpdo, args=(self._node(nid),)).start()

        return cb

    def _node(self, nid: int) -> canopen.LocalNode:
        return self.nodes[self.node_ids.index(nid)]

    def _refresh_tpdo(self, node: canopen.LocalNode) -> None:
        """Cache TPDO1's COB-ID and transmission type (None: disabled or unsupported map)."""
        try:
            cob = int.from_bytes(node.get_data(TPDO1_COMM, 1), "little")
            ttype = node.get_data(TPDO1_COMM, 2)[0]
            n_map = node.get_data(TPDO1_MAP, 0)[0]
            entry = int.from_bytes(node.get_data(TPDO1_MAP, 1), "little")
        except Exception:
            self._tpdo[_node_id(node)] = None
            return
        valid = not (cob & 0x80000000) and n_map == 1 and entry == 0x60040020
        self._tpdo[_node_id(node)] = (cob & 0x7FF, ttype) if valid and 1 <= ttype <= 240 else None

    def positions(self, wall_s: float) -> np.ndarray:
        """Position values (u32 counts) of all nodes at wall time ``wall_s`` (exact)."""
        st = self.plant.joint_state(self.plant.clock.sim_s(np.array([wall_s])))
        motor = st.motor_rad[0, : len(self.node_ids)]
        counts = np.rint(motor / (2 * np.pi) * self.config.counts_per_rev).astype(np.int64)
        values: np.ndarray = np.mod(counts + self.zero_counts, self.range)
        return values

    GRID_S = 0.00025  # interpolation grid of the motor angles
    GRID_BLOCK = 400  # grid intervals per plant evaluation (0.1 s)

    def _grid_block(self, i0: int) -> tuple[int, list[list[float]]]:
        times = (i0 + np.arange(self.GRID_BLOCK + 1)) * self.GRID_S
        st = self.plant.joint_state(self.plant.clock.sim_s(times))
        counts = st.motor_rad[:, : len(self.node_ids)] / (2 * np.pi) * self.config.counts_per_rev
        block = (i0, counts.tolist())
        self._grid = block
        return block

    def positions_list(self, wall_s: float) -> list[int]:
        """Position values of all nodes at ``wall_s``, interpolated on the look-ahead grid."""
        x = wall_s / self.GRID_S
        i = math.floor(x)
        i0, grid = self._grid
        j = i - i0
        if not 0 <= j < len(grid) - 1:
            i0, grid = self._grid_block(i)
            j = 0
        f = x - i
        rng = self.range
        return [
            (round(a + f * (b - a)) + z) % rng
            for a, b, z in zip(grid[j], grid[j + 1], self._zeros, strict=True)
        ]

    def sync_frames(self, wall_s: float | None = None) -> list[tuple[int, bytes]]:
        """The TPDOs answering one SYNC: ``(cob_id, data)`` per node that transmits."""
        wall = self.plant.clock.wall_s() if wall_s is None else wall_s
        with self._lock:
            self._sync_count += 1
            count = self._sync_count
        out: list[tuple[int, bytes]] = []
        pos = None
        for k, node in enumerate(self.nodes):
            if node.id in self._muted or node.nmt.state != "OPERATIONAL":
                continue
            tp = self._tpdo.get(_node_id(node))
            if tp is None or count % tp[1] != 0:
                continue
            if pos is None:
                pos = self.positions_list(wall)
            out.append((tp[0], _U32.pack(pos[k])))
        self.stats["syncs"] += 1
        self.stats["tpdos"] += len(out)
        return out

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        for cob, payload in self.sync_frames():
            self.network.send_message(cob, payload)

    # -- faults ---------------------------------------------------------------------------
    def mute(self, nid: int) -> None:
        """Fault: the node stops (no heartbeat, no PDOs, no SDO)."""
        node = self._node(nid)
        self._muted.add(nid)
        node.nmt.stop_heartbeat()
        self.stats["fault_mute"] += 1

    def unmute(self, nid: int) -> None:
        """The node comes back as after a power cycle: boot-up, PRE-OPERATIONAL."""
        self._muted.discard(nid)
        self._boot(self._node(nid))

    def start_fault_schedule(self) -> None:
        c = self.config
        if c.stop_heartbeat_node <= 0 or c.stop_heartbeat_after_s < 0:
            return

        def run() -> None:
            clock = self.plant.clock
            while not self._stop.wait(0.01):
                if clock.wall_s() >= c.stop_heartbeat_after_s:
                    break
            if self._stop.is_set():
                return
            self.mute(c.stop_heartbeat_node)
            if c.stop_heartbeat_for_s > 0 and not self._stop.wait(c.stop_heartbeat_for_s):
                self.unmute(c.stop_heartbeat_node)

        self._fault_thread = threading.Thread(target=run, name="encoder-faults", daemon=True)
        self._fault_thread.start()

    def close(self) -> None:
        self._stop.set()
        for node in self.nodes:
            node.nmt.stop_heartbeat()
        with contextlib.suppress(can.CanError, OSError):
            self.network.disconnect()
