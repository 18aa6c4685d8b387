"""Motor encoders: CANopen CiA 406 nodes (canopen LocalNode) read by the canopen master driver.

In one process over python-can's virtual bus, and through the emulator's socketcand server.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from drivers.encoder_canopen import EncoderCanopenDriver, parse_can_url
from drivers.errors import DriverConfigError
from sim_devices.config import CellConfig
from sim_devices.encoders import EncoderNodes
from sim_devices.plant import Plant
from sim_devices.socketcand import SocketcandServer

pytestmark = pytest.mark.timeout(60)
_channels = itertools.count()


class Cell:
    def __init__(self, toml: str = "") -> None:
        cfg = CellConfig.loads('[cell]\nprogram = "random"\n' + toml)
        self.plant = Plant.from_config(cfg)
        self.channel = f"test-enc-{next(_channels)}-{time.monotonic_ns()}"
        self.nodes = EncoderNodes(self.plant, cfg.encoders, channel=self.channel)
        self.nodes.start_fault_schedule()
        self.server = SocketcandServer(self.channel, sim_clock=self.plant.clock).start()

    def close(self) -> None:
        self.server.stop()
        self.nodes.close()


def collect(drv, seconds):
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        b = drv.read(0.05)
        if len(b):
            out.append(b)
    return out


@pytest.mark.parametrize("via", ["virtual", "socketcand"])
def test_sync_rows_match_plant_motor_angles(via):
    cell = Cell()
    try:
        url = f"virtual://{cell.channel}" if via == "virtual" else cell.server.url
        with EncoderCanopenDriver(url, sync_hz=200.0) as drv:
            nodes = drv.info["nodes"]
            assert all(v["device_type"] == 0x00020196 for v in nodes.values())
            assert nodes[1]["counts_per_rev"] == 131072
            batches = collect(drv, 1.0)
            h = drv.health()
        vals = np.concatenate([b.values for b in batches])
        st = np.concatenate([b.status for b in batches])
        assert len(vals) > 100
        assert np.mean(np.all(st == 1, axis=1)) > 0.95
        # counts follow gear ratio · joint angle: compare with the plant at "now"
        expect = cell.nodes.positions(cell.plant.clock.wall_s())
        rng = cell.nodes.range
        diff = (vals[-1] - expect + rng // 2) % rng - rng // 2
        assert np.all(np.abs(diff) < 131072 * 5)  # within a few motor turns of a moving arm
        seq = np.concatenate([b.seq for b in batches]).astype(np.int64)
        assert np.all(np.diff(seq) == 1)
        assert h.counters["heartbeat_losses"] == 0
    finally:
        cell.close()


def test_node_stops_heartbeat_then_reboots():
    cell = Cell(
        "[encoders]\nstop_heartbeat_node = 3\nstop_heartbeat_after_s = 0.6\n"
        "stop_heartbeat_for_s = 0.8\n"
    )
    try:
        with EncoderCanopenDriver(f"virtual://{cell.channel}", sync_hz=200.0) as drv:
            batches = collect(drv, 2.5)
            h = drv.health()
        assert h.counters["heartbeat_losses"] == 1
        assert h.counters["node_restarts"] == 1
        st = np.concatenate([b.status for b in batches])
        lost = (st[:, 2] & 0x4) != 0
        assert lost.any()  # channel 3 flagged while silent
        assert np.all(st[-20:, 2] == 1)  # and valid again after its restart
        assert np.all(st[:, [0, 1, 3, 4, 5]] & 1)  # other nodes never disturbed
    finally:
        cell.close()


def test_url_parsing():
    assert parse_can_url("virtual://abc")["channel"] == "abc"
    kw = parse_can_url("socketcand://127.0.0.1:29536/can0")
    assert kw == {"interface": "socketcand", "host": "127.0.0.1", "port": 29536, "channel": "can0"}
    for bad in ("can0", "socketcand://127.0.0.1/can0", "tcp://x:1/can0"):
        with pytest.raises(DriverConfigError):
            parse_can_url(bad)


def test_interpolated_positions_match_exact_plant():
    cell = Cell()
    try:
        rng = np.random.default_rng(1)
        nodes = cell.nodes
        for wall in np.sort(rng.uniform(0.0, 30.0, 400)):
            a = np.array(nodes.positions_list(float(wall)))
            b = nodes.positions(float(wall))
            d = (a - b + nodes.range // 2) % nodes.range - nodes.range // 2
            assert np.all(np.abs(d) <= 1), (wall, d)  # rounding boundary at most
    finally:
        cell.close()


def test_socketcand_node_stops_heartbeat_then_reboots():
    cell = Cell(
        "[encoders]\nstop_heartbeat_node = 3\nstop_heartbeat_after_s = 0.6\n"
        "stop_heartbeat_for_s = 0.8\n"
    )
    cell.server.sync_responder = cell.nodes.sync_frames
    try:
        with EncoderCanopenDriver(cell.server.url, sync_hz=500.0) as drv:
            batches = collect(drv, 2.5)
            h = drv.health()
        assert h.counters["heartbeat_losses"] == 1, h.counters
        assert h.counters["node_restarts"] == 1, h.counters
        st = np.concatenate([b.status for b in batches])
        assert ((st[:, 2] & 0x4) != 0).any()
        assert np.all(st[-20:, 2] == 1)
        assert np.all(st[:, [0, 1, 3, 4, 5]] & 1)
        seq = np.concatenate([b.seq for b in batches]).astype(np.int64)
        assert np.all(np.diff(seq) == 1) and len(seq) > 400
    finally:
        cell.close()


def test_sync_fast_path_reaches_every_client():
    """A second socketcand client (python-can's own) sees our SYNCs and the TPDOs."""
    import can

    cell = Cell()
    cell.server.sync_responder = cell.nodes.sync_frames
    kw = parse_can_url(cell.server.url)
    listener = can.Bus(
        interface="socketcand", host=kw["host"], port=kw["port"], channel=kw["channel"]
    )
    try:
        with EncoderCanopenDriver(cell.server.url, sync_hz=200.0) as drv:
            got: list[int] = []
            end = time.monotonic() + 1.0
            while time.monotonic() < end:
                drv.read(0.01)
                msg = listener.recv(0.01)
                while msg is not None:
                    got.append(msg.arbitration_id)
                    msg = listener.recv(0.0)
        assert got.count(0x080) > 20  # the SYNCs of the driver
        for nid in range(1, 7):
            assert got.count(0x180 + nid) > 20
    finally:
        listener.shutdown()
        cell.close()


def test_row_assembly_with_a_silent_node():
    """A node that stops answering (not yet flagged lost): each row closes when a node
    repeats, with only that node missing; never an empty row."""
    drv = EncoderCanopenDriver("virtual://unit-rows", batch_rows=1)
    drv._cob_to_k.update({0x180 + nid: nid - 1 for nid in range(1, 7)})
    for cycle in range(5):
        for nid in (1, 2, 4, 5, 6) if cycle >= 2 else (1, 2, 3, 4, 5, 6):
            drv._on_tpdo(0x180 + nid, (1000 * cycle + nid).to_bytes(4, "little"), cycle / 1e3)
    drv._lost[2] = True  # now the heartbeat watch flags node 3
    for nid in (1, 2, 4, 5, 6):
        drv._on_tpdo(0x180 + nid, (5000 + nid).to_bytes(4, "little"), 5e-3)
    rows = list(drv._rows)
    status = [r[4] for r in rows]
    assert status[:2] == [[1] * 6] * 2
    assert status[2:4] == [[1, 1, 2, 1, 1, 1]] * 2
    assert status[4:6] == [[1, 1, 6, 1, 1, 1]] * 2  # missing, and lost once flagged
    assert [r[3][0] for r in rows] == [1, 1001, 2001, 3001, 4001, 5001]
    assert [r[0] for r in rows] == list(range(6))
    drv.close()
