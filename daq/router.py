"""``daq router --config router.json5``: a zenoh router from zenoh's own configuration.

The file is what ``zenohd -c router.json5`` reads (``zenoh.Config.from_file``), so one
file serves this command and a production ``zenohd`` alike (docs/deployment.md): its
listen endpoints, TLS (``transport/link/tls``) and access control (``access_control``).
Before the session opens, the TLS files the file names are checked (readable, PEM, within
their dates, issued by its ``root_ca_certificate``), each refusal one line naming the key
and the file, exit 2.

Refusals are logged on stderr, one line each (zenoh's log, which it writes to stdout,
filtered): a client whose certificate the router's TLS refuses (another CA, expired,
none: zenoh's warnings) and, with access control enabled, a message the rules deny (zenoh
says so only at its TRACE level, beside a line for every message allowed; a thread keeps
the denials and drops the rest). Prints one JSON line when
up (``{"daq": "router", "listen": [...], "zid": ...}``) and one when stopped; SIGTERM and
SIGINT stop it, exit 0. It answers queries on ``daq/clock`` with its UTC clock, the
reference daemons measure their host's clock against (:mod:`daq.host_clock`).
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import os
import re
import sys
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from daq.bus import zenoh_reason
from daq.errors import ConfigError, TransportError
from daq.host_clock import CLOCK_KEY, serve_clock
from daq.tls import certificate_refusal, key_refusal
from edges.inputs import read_input_bytes
from edges.stop_signals import on_stop_signals

#: TLS keys of a zenoh configuration that name a file: (key, is a certificate)
TLS_FILE_KEYS: tuple[tuple[str, bool], ...] = (
    ("root_ca_certificate", True),
    ("listen_certificate", True),
    ("listen_private_key", False),
    ("connect_certificate", True),
    ("connect_private_key", False),
)
#: zenoh's log filter: warnings (TLS refusals among them), and access control's decisions
LOG_FILTER = "warn"
ACL_LOG_FILTER = "warn,zenoh::net::routing::interceptor::access_control=trace"
#: Linux fcntl F_SETPIPE_SZ (Python names it only from 3.10 on some builds), and the size
F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)
PIPE_BYTES = 1 << 20
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_TLS_REFUSAL = re.compile(
    r"invalid peer certificate: (.*?)(\. Hint:.*)?$|peer sent no certificates"
)
_ACL_REFUSAL = re.compile(r"access_control: (.* is unauthorized to .*)$")


def _get(conf: zenoh.Config, key: str) -> Any:
    """A value of a zenoh configuration (None: unset or null)."""
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # zenoh: no such key in this version
        return None


def load_router_config(path: str) -> zenoh.Config:
    """zenoh's configuration in ``path`` (JSON5), in router mode, its TLS files checked."""
    read_input_bytes(path, limit=16 << 20, error=ConfigError)  # missing, unreadable: named
    try:
        conf = zenoh.Config.from_file(path)
    except Exception as exc:
        raise ConfigError(f"{path}: {zenoh_reason(exc)}") from None
    mode = _get(conf, "mode")
    if mode not in (None, "router"):
        raise ConfigError(f"{path}: key 'mode': daq router runs a router, got {mode!r}")
    conf.insert_json5("mode", '"router"')
    ca = _get(conf, "transport/link/tls/root_ca_certificate")
    for key, is_cert in TLS_FILE_KEYS:
        value = _get(conf, f"transport/link/tls/{key}")
        if not value:
            continue
        file = str(value)  # zenoh reads a relative path from the working directory
        if is_cert:
            refusal = certificate_refusal(file, ca if key != "root_ca_certificate" else None)
        else:
            refusal = key_refusal(file)
        if refusal is not None:
            raise ConfigError(f"{path}: key 'transport/link/tls/{key}': {refusal}")
    return conf


def refusal_line(raw: str) -> str | None:
    """The line to print for one line of zenoh's log (None: drop it): refusals said
    plainly, other warnings and errors as they are, access control's allowances dropped."""
    line = _ANSI.sub("", raw).rstrip()
    m = _TLS_REFUSAL.search(line)
    if m is not None:
        why = m.group(1) or "no client certificate"
        return f"daq router: refused a TLS client: {why}"
    m = _ACL_REFUSAL.search(line)
    if m is not None:
        return f"daq router: refused: {m.group(1)}"
    if " WARN " in line or " ERROR " in line:
        return line
    return None


class LogFilter:
    """zenoh's log through ``refusal_line``. zenoh's Rust logger writes to file
    descriptor 1 (stdout): fd 1 becomes a pipe read by a thread, which writes what it
    keeps to stderr; ``sys.stdout`` meanwhile points at the real stdout, so the JSON
    lines of the command stay there, alone."""

    def __init__(self, keep: Callable[[str], str | None] = refusal_line) -> None:
        self._keep = keep
        sys.stdout.flush()
        self._saved = os.dup(1)
        read_fd, write_fd = os.pipe()
        # zenoh's log thread waits when the pipe is full: ≈ 0.7 s of a 3 x 1 kHz cell's
        # lines (one per message allowed) held for a reader short of CPU
        with contextlib.suppress(OSError):
            fcntl.fcntl(write_fd, F_SETPIPE_SZ, PIPE_BYTES)
        os.dup2(write_fd, 1)
        os.close(write_fd)
        self._old_stdout = sys.stdout
        sys.stdout = open(os.dup(self._saved), "w", buffering=1, encoding="utf-8")  # noqa: SIM115
        self._reader = open(read_fd, encoding="utf-8", errors="replace")  # noqa: SIM115
        self._thread = threading.Thread(target=self._run, name="router-log", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for raw in self._reader:
            kept = self._keep(raw)
            if kept is not None:
                print(kept, file=sys.stderr, flush=True)

    def close(self) -> None:
        os.dup2(self._saved, 1)  # the pipe's last writer gone: the thread reads its end
        os.close(self._saved)
        self._thread.join(timeout=5.0)
        self._reader.close()
        ours, sys.stdout = sys.stdout, self._old_stdout
        ours.close()


def main_router(args: argparse.Namespace) -> int:
    """``daq router``: serve until SIGTERM/SIGINT; exit 0."""
    conf = load_router_config(args.config)
    acl = bool(_get(conf, "access_control/enabled"))
    log = LogFilter()
    try:
        zenoh.init_log_from_env_or(ACL_LOG_FILTER if acl else LOG_FILTER)
        stop = threading.Event()
        on_stop_signals(stop.set)  # not stop.set() in the handler: edges/stop_signals.py
        try:
            session = zenoh.open(conf)
        except Exception as exc:
            why = zenoh_reason(exc)
            raise TransportError(f"{args.config}: cannot start the router: {why}") from None
        try:
            zid = str(session.info.zid())
            # the cell's clock reference: daemons measure their host's offset against it
            serve_clock(session, f"router {zid}")
            up = {
                "daq": "router",
                "config": args.config,
                "listen": _get(conf, "listen/endpoints") or [],
                "access_control": acl,
                "zid": zid,
                "clock_key": CLOCK_KEY,
            }
            print(json.dumps(up), flush=True)
            stop.wait()
        finally:
            session.close()
        print(json.dumps({"daq": "router stopped", "signal": True}), flush=True)
    finally:
        log.close()
    return 0
