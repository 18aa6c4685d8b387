"""A zenoh client for tests/test_cell_hosts.py, run inside a test's network namespace.

    python tests/daq/hosts_probe.py '{"role": "...", "endpoint": "tls/10.231.2.2:7447", ...}'

Roles (one JSON line on stdout says what happened):

* ``connect``: open a client session with the given certificate (or none); zenoh's
  session, not ``daq``'s, so no local check stands between it and the router.
* ``twin``: with the twin's certificate, subscribe to the cell's data for ``seconds``,
  publish JSON on ``twin/<cell>/robot/robot1/health`` and try to inject into the cell's
  keys: a foreign batch on the tracker's data key, JSON under an ``intruder`` device.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import zenoh

INJECTED = b"DQC1 injected by a certificate without publish right"


def session(spec: dict[str, Any]) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([spec["endpoint"]]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    tls = {"root_ca_certificate": spec["ca"]}
    if spec.get("cert"):
        tls |= {"connect_certificate": spec["cert"], "connect_private_key": spec["key"]}
        tls["enable_mtls"] = True
    for k, v in tls.items():
        conf.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
    return zenoh.open(conf)


def connect(spec: dict[str, Any]) -> dict[str, Any]:
    try:
        s = session(spec)
    except Exception as exc:
        return {"opened": False, "error": str(exc).splitlines()[0][:200]}
    got: list[str] = []
    sub = s.declare_subscriber(f"cell/{spec['cell']}/**", lambda x: got.append(str(x.key_expr)))
    time.sleep(1.0)
    sub.undeclare()
    s.close()
    return {"opened": True, "received": len(got)}


def twin(spec: dict[str, Any]) -> dict[str, Any]:
    from daq.bus import DATA_ENCODING

    cell = spec["cell"]
    s = session(spec)
    got: list[str] = []
    sub = s.declare_subscriber(f"cell/{cell}/**", lambda x: got.append(str(x.key_expr)))
    t_end = time.monotonic() + float(spec["seconds"])
    puts = 0
    while time.monotonic() < t_end and puts < 1000:  # bounded by count and time
        doc = {"twin": "probe", "n": puts}
        s.put(f"twin/{cell}/robot/robot1/health", json.dumps(doc))
        s.put(f"cell/{cell}/robot/robot1/tracker/samples", INJECTED, encoding=DATA_ENCODING)
        s.put(f"cell/{cell}/robot/robot1/intruder/health", json.dumps({"intruder": puts}))
        puts += 1
        time.sleep(0.1)
    sub.undeclare()
    s.close()
    return {"received": len(got), "puts": puts}


def main() -> int:
    spec = json.loads(sys.argv[1])
    out = connect(spec) if spec["role"] == "connect" else twin(spec)
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
