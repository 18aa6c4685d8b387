"""`sim-cell serve` as a real process: every device reachable by its own driver and by an
independent client (pymodbus client, canopen master, plain socket), per docs/protocols.md."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytestmark = pytest.mark.timeout(120)


def start_cell(tmp_path, toml: str = "", duration: float = 30.0, n_records: int = 4):
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[cell]\nprogram = "random"\n' + toml)
    truth = tmp_path / "truth.toml"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sim_devices.cli",
            "serve",
            "--config",
            str(cfg),
            "--duration",
            str(duration),
            "--truth",
            str(truth),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    records = []
    deadline = time.monotonic() + 30
    while len(records) < n_records and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        records.append(json.loads(line))
    assert len(records) == n_records, proc.stderr.read()
    return proc, {(r["kind"], r["protocol"]): r for r in records}, truth


def stop_cell(proc):
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cell")
    proc, recs, truth = start_cell(tmp)
    yield recs, truth
    assert stop_cell(proc) == 0


def test_records_and_truth_file(cell):
    recs, truth = cell
    assert recs[("grating_reader", "modbus-rtu")]["unit_id"] == 1
    assert os.path.exists(recs[("grating_reader", "modbus-rtu")]["path"])
    assert recs[("laser_tracker", "ascii-tcp")]["url"].startswith("socket://127.0.0.1:")
    assert recs[("motor_encoders", "canopen-socketcand")]["node_ids"] == [1, 2, 3, 4, 5, 6]
    import tomllib

    doc = tomllib.loads(truth.read_text())
    assert {"robot", "strip", "plant", "program", "config"} <= set(doc)


def test_independent_pymodbus_client(cell):
    from pymodbus.client import ModbusSerialClient

    recs, _ = cell
    c = ModbusSerialClient(recs[("grating_reader", "modbus-rtu")]["path"], timeout=0.5)
    assert c.connect()
    try:
        info = c.read_holding_registers(0, count=16, device_id=1)
        assert info.registers[0] == 0x4752 and info.registers[2] == 6
        r = c.readwrite_registers(
            read_address=0x100,
            read_count=5 + 20 * 6,
            write_address=0x100,
            values=[0, 0],
            device_id=1,
        )
        n = r.registers[2]
        assert 1 <= n <= 6
        bad = c.read_holding_registers(0x2000, count=2, device_id=1)
        assert bad.isError() and bad.exception_code == 2
    finally:
        c.close()


def test_independent_canopen_master(cell):
    import canopen

    recs, _ = cell
    r = recs[("motor_encoders", "canopen-socketcand")]
    net = canopen.Network()
    net.connect(interface="socketcand", host=r["host"], port=r["port"], channel=r["channel"])
    try:
        node = net.add_node(2, None)
        raw = node.sdo.upload(0x1000, 0)
        assert int.from_bytes(raw, "little") == 0x00020196
        assert int.from_bytes(node.sdo.upload(0x6001, 0), "little") == 131072
        got = []
        net.subscribe(0x182, lambda cid, data, ts: got.append(bytes(data)))
        net.nmt.send_command(0x01)
        for _ in range(20):
            net.sync.transmit()
            time.sleep(0.01)
        time.sleep(0.1)
        assert len(got) >= 10 and all(len(d) == 4 for d in got)
    finally:
        net.disconnect()


def test_plain_socket_tracker(cell):
    recs, _ = cell
    r = recs[("laser_tracker", "ascii-tcp")]
    with socket.create_connection((r["host"], r["port"]), timeout=3) as s:
        f = s.makefile("rwb")
        f.write(b"*IDN?\n")
        f.flush()
        assert f.readline().startswith(b"EMULATED,LT500-SIM,")
        f.write(b"STREAM:RATE 100\nSTREAM:START\n")
        f.flush()
        lines = [f.readline() for _ in range(20)]
        assert sum(ln.startswith(b"D,") for ln in lines) >= 15


def test_all_three_drivers_together_at_1khz(cell):
    from drivers.registry import open_driver

    recs, _ = cell
    specs = [
        ("grating_modbus", recs[("grating_reader", "modbus-rtu")]["path"], {}),
        ("tracker_ascii", recs[("laser_tracker", "ascii-serial")]["path"], {"rate_hz": 1000.0}),
        (
            "encoder_canopen",
            recs[("motor_encoders", "canopen-socketcand")]["url"],
            {"sync_hz": 1000.0},
        ),
    ]
    results = {}

    def run(name, url, opts):
        with open_driver(name, url, **opts) as drv:
            drv.read(0.2)
            n, t0 = 0, time.monotonic()
            seqs = []
            while time.monotonic() - t0 < 3.0:
                b = drv.read(0.05)
                n += len(b)
                seqs.append(b.seq)
            results[name] = (n / (time.monotonic() - t0), drv.health(), np.concatenate(seqs))

    threads = [threading.Thread(target=run, args=s) for s in specs]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    for name, (rate, health, seq) in results.items():
        assert rate > 300, (name, rate, health.counters)  # 1 kHz nominal; busy shared machine
        assert health.counters["lost_samples"] == 0, (name, health.counters)
        assert np.all(np.diff(seq.astype(np.int64)) == 1), name


def _read_all_three(recs, rate_hz, settle_s, seconds):
    """Open the three drivers at once (threads, as the daemon does), let them connect and
    catch up, then read a window of ``seconds``; per driver: rate, health, sequences."""
    from drivers.registry import open_driver

    specs = [
        ("grating_modbus", recs[("grating_reader", "modbus-rtu")]["path"], {}),
        ("tracker_ascii", recs[("laser_tracker", "ascii-serial")]["path"], {"rate_hz": rate_hz}),
        (
            "encoder_canopen",
            recs[("motor_encoders", "canopen-socketcand")]["url"],
            {"sync_hz": rate_hz},
        ),
    ]
    results = {}
    ready = threading.Barrier(len(specs))

    def run(name, url, opts):
        with open_driver(name, url, **opts) as drv:
            t = time.monotonic()
            while time.monotonic() - t < settle_s:
                drv.read(0.05)
            ready.wait(60)
            n, seqs, t0 = 0, [], time.monotonic()
            while time.monotonic() - t0 < seconds:
                b = drv.read(0.05)
                n += len(b)
                seqs.append(b.seq)
            h = drv.health()
            results[name] = {
                "rate": n / (time.monotonic() - t0),
                "health": h,
                "seq": np.concatenate(seqs).astype(np.int64),
            }

    threads = [threading.Thread(target=run, args=s) for s in specs]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    return results


def test_all_three_steady_state_no_loss_at_300hz(tmp_path):
    """All three devices at once at 300 Hz each (the 1 kHz target is the benchmark's,
    benchmarks/bench_drivers.py): after the drivers connect, not one sample is lost,
    sequences are contiguous and each device keeps its rate."""
    proc, recs, _ = start_cell(tmp_path, "[grating]\nrate_hz = 300.0\n", duration=60.0)
    try:
        time.sleep(1.0)
        results = _read_all_three(recs, 300.0, settle_s=1.5, seconds=4.0)
    finally:
        stop_cell(proc)
    assert set(results) == {"grating_modbus", "tracker_ascii", "encoder_canopen"}
    for name, r in results.items():
        counters = r["health"].counters
        assert counters["lost_samples"] == 0, (name, counters)
        assert np.all(np.diff(r["seq"]) == 1), name
        assert r["rate"] > 0.8 * 300, (name, r["rate"], counters)
        assert r["health"].state == "connected"


def test_duration_stops_by_itself_and_ptys_go(tmp_path):
    proc, recs, _ = start_cell(tmp_path, "[tracker]\nserial = false\n", 2.0, n_records=3)
    path = recs[("grating_reader", "modbus-rtu")]["path"]
    proc.wait(timeout=30)
    assert proc.returncode == 0
    assert not os.path.exists(path)
