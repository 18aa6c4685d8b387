"""daq.config: defaults, precedence (args > DAQ_* env > file), errors that name the key."""

from __future__ import annotations

import pytest

from daq import config as cfg
from daq.errors import ConfigError

GOOD = """
[cell]
name = "c1"
robot = "r1"

[zenoh]
listen = ["tcp/127.0.0.1:17000"]

[recording]
enabled = true
path = "x.mcap"

[[device]]
name = "grating"
driver = "grating_modbus"
url = "socket://127.0.0.1:5020"
rate_hz = 1000
joints = [1, 2, 3, 4, 5, 6]
options = { unit_id = 3 }

[[device]]
name = "tracker"
driver = "tracker_ascii"
url = "socket://127.0.0.1:5025"
robot = "r2"
[device.channels]
tcp = ["x_mm", "y_mm", "z_mm"]
"""


def test_defaults_and_values(tmp_path):
    p = tmp_path / "cell.toml"
    p.write_text(GOOD)
    c = cfg.load(p, environ={})
    assert c.cell.name == "c1"
    assert c.zenoh.mode == "peer" and c.zenoh.listen == ("tcp/127.0.0.1:17000",)
    assert not c.zenoh.multicast_scouting and not c.zenoh.gossip_scouting
    assert c.zenoh.congestion_control == "block" and c.zenoh.tx_queue_batches == 16
    assert c.devices[0].robot == "r1" and c.devices[0].rate_hz == 1000.0
    assert c.devices[0].joints == (1, 2, 3, 4, 5, 6)
    assert c.devices[0].options == {"unit_id": 3}
    assert c.devices[1].robot == "r2"
    assert c.devices[1].channels == (cfg.ChannelGroup("tcp", ("x_mm", "y_mm", "z_mm")),)
    assert c.recording.enabled and c.recording.compression == "zstd"


def test_precedence_args_over_env_over_file(tmp_path):
    p = tmp_path / "cell.toml"
    p.write_text(GOOD)
    env = {"DAQ_ZENOH_LISTEN": "tcp/127.0.0.1:1,tcp/127.0.0.1:2", "DAQ_CELL_NAME": "fromenv"}
    c = cfg.load(p, environ=env)
    assert c.zenoh.listen == ("tcp/127.0.0.1:1", "tcp/127.0.0.1:2")
    assert c.cell.name == "fromenv"
    c = cfg.load(p, environ=env, overrides={"cell": {"name": "fromargs"}})
    assert c.cell.name == "fromargs"
    # TOML-typed env values
    c = cfg.load(p, environ={"DAQ_PUBLISH_MAX_BATCH_AGE_S": "0.01"})
    assert c.publish.max_batch_age_s == 0.01
    # DAQ_CONFIG names the file
    assert cfg.load(environ={"DAQ_CONFIG": str(p)}).cell.name == "c1"


@pytest.mark.parametrize(
    "patch, message",
    [
        (("rate_hz = 1000", 'rate_hz = "1000"'), "#1 'grating': key 'rate_hz': expected a number"),
        (('name = "c1"', 'name = "c/1"'), "[cell]: key 'name'"),
        (("listen = [", "bogus = 1\nlisten = ["), "[zenoh]: unknown key 'bogus'"),
        (('path = "x.mcap"', 'compression = "gzip"'), "key 'compression': must be one of"),
        (("tcp = [", "health = ["), "'health' is reserved"),
        (('driver = "tracker_ascii"\n', ""), "#2 'tracker': key 'driver': missing"),
        (
            ("listen = [", "tx_queue_batches = 17\nlisten = ["),
            "key 'tx_queue_batches': must be <= 16",
        ),
    ],
)
def test_errors_name_the_key(tmp_path, patch, message):
    p = tmp_path / "cell.toml"
    p.write_text(GOOD.replace(*patch, 1))
    with pytest.raises(ConfigError) as info:
        cfg.load(p, environ={})
    assert message in str(info.value)
    assert str(p) in str(info.value)


def test_env_errors_name_the_variable(tmp_path):
    p = tmp_path / "cell.toml"
    p.write_text(GOOD)
    with pytest.raises(ConfigError, match=r"DAQ_ZENOH_MODE.*'mode'"):
        cfg.load(p, environ={"DAQ_ZENOH_MODE": "satellite"})
    with pytest.raises(ConfigError, match="DAQ_ZENOH_NOPE"):
        cfg.load(p, environ={"DAQ_ZENOH_NOPE": "1"})
    with pytest.raises(ConfigError, match="command-line argument"):
        cfg.load(p, environ={}, overrides={"recording": {"chunk_size_bytes": 3}})


def test_client_mode_needs_a_router():
    with pytest.raises(ConfigError, match="connect"):
        cfg.loads('[zenoh]\nmode = "client"\n')
    c = cfg.loads('[zenoh]\nmode = "client"\nconnect = ["tcp/127.0.0.1:7447"]\n')
    assert c.zenoh.listen == ()


def test_a_list_key_takes_a_comma_separated_string_in_the_file_too():
    c = cfg.loads(
        '[zenoh]\nlisten = "tcp/127.0.0.1:1, tcp/127.0.0.1:2"\nconnect = ""\n'
        '[[device]]\nname = "t"\ndriver = "tracker_ascii"\nurl = "socket://h:1"\n'
        'channels = { xyz = "x_mm,y_mm, z_mm" }\n'
    )
    assert c.zenoh.listen == ("tcp/127.0.0.1:1", "tcp/127.0.0.1:2") and c.zenoh.connect == ()
    assert c.devices[0].channels == (cfg.ChannelGroup("xyz", ("x_mm", "y_mm", "z_mm")),)
