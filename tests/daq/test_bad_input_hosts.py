"""Bad configuration of a cell over several hosts (docs/deployment.md): one line on stderr
naming the file, key or endpoint, exit 2, no traceback, nothing left running.

``daq run --config cell.toml`` and ``daq echo`` with TLS settings that cannot work (a
missing certificate file, an expired one, one from another CA, a certificate without its
key, ``tls/`` without a CA, an unknown key, a router nobody answers at), and ``daq
router --config`` with a JSON5 file that names a missing or expired certificate, a key
zenoh does not know, or a mode other than router. The certificates come from
scripts/make-test-pki.sh. Loopback only: the router endpoints are free 127.0.0.1 ports.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT_S = 60


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    d = tmp_path_factory.mktemp("hosts")
    subprocess.run(
        [str(ROOT / "scripts/make-test-pki.sh"), str(d / "pki")],
        check=True,
        capture_output=True,
        timeout=60,
    )
    yield d


def _refused(work: Path, args: list[str], *words: str) -> str:
    env = {k: v for k, v in os.environ.items() if not k.startswith("DAQ_")}
    env["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run(
        [sys.executable, "-m", "daq.cli", *args],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, err, proc.stdout[-2000:])
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    if os.environ.get("SHOW_MESSAGES"):
        print(f"\n{' '.join(args)}\n    -> {err}")
    missing = [w for w in words if w not in err]
    assert not missing, (missing, err)
    return err


def _cell(work: Path, name: str, zenoh: str) -> str:
    """A one-device cell TOML (the in-process fake device) with ``zenoh`` as its table."""
    text = f"""[cell]
name = "cell1"

[zenoh]
{zenoh}

[[device]]
name = "fake"
driver = "daq.testing:FakeDriver"
url = "fake://"
"""
    (work / name).write_text(text, encoding="utf-8")
    return name


def _client(port: int, cert: str = "daemon", ca: str = "pki/ca.pem", key: str | None = None) -> str:
    return "\n".join(
        (
            'mode = "client"',
            f'connect = ["tls/127.0.0.1:{port}"]',
            f'tls_ca = "{ca}"',
            f'tls_certificate = "pki/{cert}.pem"',
            f'tls_private_key = "pki/{key or cert}.key"',
        )
    )


@pytest.mark.parametrize(
    ("label", "zenoh", "words"),
    [
        ("missing certificate", "missing", ["cell.toml", "tls_certificate", "pki/missing.pem"]),
        ("expired", "expired", ["tls_certificate", "pki/expired.pem", "expired on 2020-01-02"]),
        ("wrong CA", "wrong-ca", ["tls_certificate", "pki/wrong-ca.pem", "not issued by the CA"]),
    ],
)
def test_daq_run_refuses_a_certificate_that_cannot_work(
    work: Path, label: str, zenoh: str, words: list[str]
) -> None:
    if zenoh == "missing":
        text = _client(_free_port()).replace("pki/daemon.pem", "pki/missing.pem")
    else:
        text = _client(_free_port(), cert=zenoh)
    _refused(work, ["run", "--config", _cell(work, "cell.toml", text)], *words)


def test_daq_run_refuses_half_or_unknown_tls_settings(work: Path) -> None:
    port = _free_port()
    no_key = _client(port).replace('tls_private_key = "pki/daemon.key"', "")
    _refused(work, ["run", "--config", _cell(work, "a.toml", no_key)], "a.toml", "tls_private_key")
    no_ca = _client(port).replace('tls_ca = "pki/ca.pem"', "")
    _refused(work, ["run", "--config", _cell(work, "b.toml", no_ca)], "b.toml", "'tls_ca'")
    unknown = _client(port) + '\ntls_cert = "pki/daemon.pem"'
    _refused(work, ["run", "--config", _cell(work, "c.toml", unknown)], "c.toml", "tls_cert")
    not_key = _client(port, key="daemon").replace("pki/daemon.key", "pki/daemon.pem")
    _refused(work, ["run", "--config", _cell(work, "d.toml", not_key)], "tls_private_key")


def test_a_router_nobody_answers_at_is_named(work: Path) -> None:
    port = _free_port()
    cell = _cell(work, "cell.toml", _client(port))
    _refused(work, ["run", "--config", cell], "[zenoh] connect", f"tls/127.0.0.1:{port}")
    _refused(
        work,
        ["echo", "--config", cell, "--duration", "1"],
        "[zenoh] connect",
        f"tls/127.0.0.1:{port}",
    )


def _router_file(work: Path, name: str, tls: str, extra: str = "") -> str:
    text = f"""{{
  mode: "router",
  listen: {{ endpoints: ["tls/127.0.0.1:{_free_port()}"] }},
  scouting: {{ multicast: {{ enabled: false }} }},
  transport: {{ link: {{ tls: {{ {tls} }} }} }},
  {extra}
}}
"""
    (work / name).write_text(text, encoding="utf-8")
    return name


GOOD_TLS = (
    'root_ca_certificate: "pki/ca.pem", listen_certificate: "pki/router.pem", '
    'listen_private_key: "pki/router.key", enable_mtls: true'
)


def test_daq_router_refuses_bad_configuration(work: Path) -> None:
    missing = _router_file(work, "r1.json5", GOOD_TLS.replace("pki/router.pem", "pki/no.pem"))
    _refused(work, ["router", "--config", missing], "r1.json5", "listen_certificate", "no.pem")
    expired = _router_file(work, "r2.json5", GOOD_TLS.replace("pki/router.pem", "pki/expired.pem"))
    _refused(work, ["router", "--config", expired], "r2.json5", "expired on 2020-01-02")
    unknown = _router_file(work, "r3.json5", GOOD_TLS, extra="no_such_key: 1,")
    _refused(work, ["router", "--config", unknown], "r3.json5", "no_such_key")
    _router_file(work, "r4.json5", GOOD_TLS)
    text = (work / "r4.json5").read_text(encoding="utf-8")
    (work / "r4.json5").write_text(text.replace('"router"', '"client"'), encoding="utf-8")
    _refused(work, ["router", "--config", "r4.json5"], "r4.json5", "'mode'", "client")
    _refused(work, ["router", "--config", "absent.json5"], "absent.json5")


def test_router_log_keeps_refusals_and_drops_allowances() -> None:
    """zenoh's log lines as ``daq router`` sees them (ANSI colours included)."""
    from daq.router import refusal_line

    tls = (
        "\x1b[2m2026-11-27T02:29:12Z\x1b[0m \x1b[33m WARN\x1b[0m acc-0 zenoh_link_tls::unicast: "
        "invalid peer certificate: UnknownIssuer. Hint: increase the system open file limit."
    )
    assert refusal_line(tls) == "daq router: refused a TLS client: UnknownIssuer"
    none = "2026 WARN acc-0 zenoh_link_tls::unicast: peer sent no certificates. Hint: x"
    assert refusal_line(none) == "daq router: refused a TLS client: no client certificate"
    acl = (
        "2026 TRACE rx-0 zenoh::net::routing::interceptor::access_control: ab on "
        "Interface(lo)+CertCommonName(twin)+Transport(Tls)+ab is unauthorized to Put (ingress) on "
        "cell/cell1/x"
    )
    assert refusal_line(acl) == (
        "daq router: refused: ab on Interface(lo)+CertCommonName(twin)+Transport(Tls)+ab "
        "is unauthorized to Put (ingress) on cell/cell1/x"
    )
    allowed = acl.replace("is unauthorized", "is authorized")
    assert refusal_line(allowed) is None
    assert refusal_line("2026 DEBUG x: Access control is enabled") is None
    other = "2026  WARN zenoh::net::runtime::orchestrator: Unable to connect to tls/1.2.3.4:7447!"
    assert refusal_line(other) == other
