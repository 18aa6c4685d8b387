"""zenoh publishing: a separate subscriber process gets every batch, in order, decodes it
from the schema it fetched with a query; the schema query answers globs."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from daq.bus import (
    ChannelPublisher,
    Receiver,
    SchemaServer,
    fetch_schema,
    open_session,
    schema_key,
    zenoh_config,
)
from daq.columnar import Column, StreamSchema
from daq.config import ZenohConfig
from daq.testing import free_port, loopback_sink, loopback_source

KEY = "cell/t/robot/r/dev/ch"
SCHEMA = StreamSchema(
    KEY,
    (
        Column("seq", "uint64"),
        Column("t_mapped_ns", "int64", unit="ns", clock="host_utc"),
        Column("v", "float64", (2,), unit="mm"),
    ),
)


def test_config_is_loopback_only():
    conf = zenoh_config(loopback_source(7447))

    def get(path):
        return json.loads(conf.get_json(path))

    assert get("scouting/multicast/enabled") is False
    assert get("scouting/gossip/enabled") is False
    assert get("listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert get("transport/shared_memory/enabled") is False
    assert get("transport/link/tx/queue/size/data") == 16  # the daemon's bursts (docs/daq.md)


@pytest.mark.timeout(60)
def test_subscriber_process_gets_every_batch_in_order():
    port = free_port()
    session = open_session(loopback_source(port))
    try:
        schemas = SchemaServer(session, "cell/t")
        pub = ChannelPublisher(session, SCHEMA, schemas=schemas)
        sub = subprocess.Popen(
            [
                sys.executable, "-m", "daq.cli", "echo", "cell/t/**", "--stats", "--ready",
                "--idle", "2", "--duration", "30", "--connect", f"tcp/127.0.0.1:{port}",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        assert "ready" in sub.stderr.readline()
        deadline = time.monotonic() + 10
        while not pub._pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        n_batches, per = 2000, 10
        for i in range(n_batches):
            seq = np.arange(i * per, (i + 1) * per, dtype=np.uint64)
            pub.publish({"seq": seq, "t_mapped_ns": np.full(per, time.time_ns()),
                         "v": np.zeros((per, 2))})  # fmt: skip
        out, err = sub.communicate(timeout=40)
        assert sub.returncode == 0, err
        stats = json.loads(out.strip().splitlines()[-1])["keys"][KEY]
        assert stats["samples"] == n_batches * per
        assert stats["lost_batches"] == 0 and stats["seq_gaps"] == 0
        assert stats["seq_breaks"] == 0 and stats["out_of_order"] == 0
        assert stats["first_seq"] == 0 and stats["last_seq"] == n_batches * per - 1
    finally:
        session.close()


@pytest.mark.timeout(30)
def test_schema_query_and_in_process_receiver():
    port = free_port()
    src = open_session(loopback_source(port))
    dst = open_session(loopback_sink(port))
    try:
        schemas = SchemaServer(src, "cell/t")
        pub = ChannelPublisher(src, SCHEMA, schemas=schemas)
        other = StreamSchema("cell/t/robot/r/dev2/ch", SCHEMA.columns[:1])
        ChannelPublisher(src, other, schemas=schemas)
        time.sleep(0.3)
        assert fetch_schema(dst, KEY) == SCHEMA
        replies = [r.ok for r in dst.get("cell/t/**/@schema", timeout=2) if r.ok]
        assert sorted(str(r.key_expr) for r in replies) == sorted(
            [schema_key(KEY), schema_key(other.key)]
        )
        recv = Receiver(dst, "cell/t/**")
        time.sleep(0.3)
        pub.publish({"seq": np.arange(3), "t_mapped_ns": np.arange(3), "v": np.ones((3, 2))})
        got = recv.receive(5)
        assert got is not None and got.key == KEY and got.header.n_samples == 3
        np.testing.assert_array_equal(got.columns["v"], np.ones((3, 2)))
        recv.close()
    finally:
        dst.close()
        src.close()


@pytest.mark.timeout(60)
def test_router_mode_and_record_process(tmp_path):
    """Daemon and subscribers as zenoh clients of a router (what zenohd does across hosts;
    here a Python session in router mode), and ``daq record`` as a separate recorder."""
    from daq.config import load
    from daq.daemon import Daemon
    from daq.recording_reader import scan
    from daq.testing import FakeDriver

    rport = free_port()
    router = open_session(ZenohConfig(mode="router", listen=(f"tcp/127.0.0.1:{rport}",)))
    endpoint = f"tcp/127.0.0.1:{rport}"
    cfg_path = tmp_path / "cell.toml"
    cfg_path.write_text(
        f'[cell]\nname = "rt"\n[zenoh]\nmode = "client"\nconnect = ["{endpoint}"]\n'
        '[[device]]\nname = "fake"\ndriver = "daq.testing:FakeDriver"\nurl = "fake://"\n'
    )
    out = tmp_path / "rec.mcap"
    common = ["--mode", "client", "--connect", endpoint]
    echo = subprocess.Popen(
        [sys.executable, "-m", "daq.cli", "echo", "cell/**", "--stats", "--ready",
         "--duration", "30", "--idle", "2", *common],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    rec = subprocess.Popen(
        [sys.executable, "-m", "daq.cli", "record", "cell/**", "-o", str(out),
         "--duration", "6", *common],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert "ready" in echo.stderr.readline()
        assert json.loads(rec.stdout.readline())["recording"] == str(out)
        cfg = load(cfg_path, environ={})
        with Daemon(cfg, driver_factory=lambda dev: FakeDriver(dev.url)) as daemon:
            t = threading.Thread(target=daemon.run, args=(3.0,))
            t.start()
            time.sleep(1.0)
            alive = [str(r.ok.key_expr) for r in router.liveliness().get("cell/**", timeout=2)]
            t.join()
            # the undeclaration reaches the router asynchronously: wait for it (bounded)
            deadline = time.monotonic() + 5
            while True:
                gone = [str(r.ok.key_expr) for r in router.liveliness().get("cell/**", timeout=1)]
                if not gone or time.monotonic() > deadline:
                    break
                time.sleep(0.1)
        assert alive == ["cell/rt/robot/robot1/fake"] and gone == []  # token per device
        e_out, e_err = echo.communicate(timeout=30)
        rec.communicate(timeout=30)
    finally:
        router.close()
    stats = json.loads(e_out.strip().splitlines()[-1])
    key = "cell/rt/robot/robot1/fake/samples"
    assert stats["keys"][key]["samples"] > 1500, e_err
    assert stats["keys"][key]["seq_gaps"] == 0
    assert "cell/rt/robot/robot1/fake/health" in stats["health"]
    recording, counts = scan(out)
    assert recording.complete and counts[key] > 100
    assert counts["cell/rt/robot/robot1/fake/health"] >= 2


def test_a_script_that_never_closes_its_receiver_still_exits():
    """zenoh runs subscriber callbacks on a non-daemon thread: a Receiver left open used
    to keep the interpreter from ending; it is closed at shutdown now."""
    import textwrap

    script = textwrap.dedent(
        """
        from daq.bus import Receiver, open_session
        from daq.testing import free_port, loopback_source

        session = open_session(loopback_source(free_port()))
        print(Receiver(session, "cell/**").receive(0.2))
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=30
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "None"
