"""``twin run`` live: collect the campaign from the daemon's zenoh keys, then publish the twin.

Collection subscribes to the daemon's data keys (default ``cell/**``; schemas by query),
accumulates the grating, tracker and encoder streams and prints progress (samples, dwells,
sweeps, Home returns, poses found so far). The campaign is over when poses have been found
and the gratings have been still for ``--idle-s``, when no data came for ``--idle-s`` (the
source stopped), or after ``--collect-s``. The same
pipeline as a replay then runs on the collected streams (:func:`run_twin`).

The live twin (docs/topics.md, "Twin keys") is published per grating batch, at the grating
rate, on ``twin/<cell>/robot/<robot>/state`` (columnar ``daq.columnar.v1``, schema by
``<key>/@schema``): per grating sample its mapped time, the joint angles from the scale
calibration, the TCP from the calibrated model with its effects, the flange pose
(position and quaternion), and the encoder-minus-grating joint difference (the encoder
sample nearest in mapped time). ``twin/<cell>/robot/<robot>/health`` (JSON, once a second)
carries the end-to-end latency: publication time minus the grating sample's mapped time
(latch → twin), p50/p99/max over the period, for samples whose clock map had settled
(all samples, with ``clock_settled: false``, while none has).
The batches that arrived together are evaluated in one vectorized call (one TCP, flange
and scale evaluation per drain, not per 1 ms batch), and published as one batch.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from calibration.errors import CalibrationError
from calibration.phase_detection import PhaseOptions, find_dwells, find_phases
from calibration.streams import CellStreams, StreamBuilder, pick_streams

TWIN_PREFIX = "twin"


class LiveTwinError(CalibrationError):
    """The live twin cannot start (no grating stream where it was told to look)."""


def twin_keys(cell: str, robot: str) -> dict[str, str]:
    base = f"{TWIN_PREFIX}/{cell}/robot/{robot}"
    return {"state": f"{base}/state", "health": f"{base}/health"}


def _zenoh_config(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from daq.config import ZenohConfig

    # a client of the daemon by default: the daemon's session then routes the twin's keys
    # to every session connected to it (two peers connected to the daemon are not routed
    # to each other: docs/topics.md, "One endpoint")
    mode = getattr(args, "mode", None) or "client"
    return ZenohConfig(
        mode=mode,
        listen=() if mode == "client" else tuple(e for e in (args.listen or ()) if e != "none"),
        connect=tuple(e for e in (args.connect or ["tcp/127.0.0.1:7447"]) if e != "none"),
    )


class LiveTwin:
    """One zenoh session: collect the campaign, then publish the twin."""

    def __init__(self, args: argparse.Namespace, say) -> None:  # type: ignore[no-untyped-def]
        from daq.bus import Receiver, open_session

        self.args = args
        self.say = say
        self.session = open_session(_zenoh_config(args))
        self.receiver = Receiver(self.session, args.key)
        self.builders: dict[str, StreamBuilder] = {}
        self.closed = False

    # -- collection ------------------------------------------------------------------
    def _add(self, got) -> None:  # type: ignore[no-untyped-def]
        b = self.builders.get(got.key)
        if b is None:
            b = self.builders[got.key] = StreamBuilder(got.key, got.schema.to_json())
        if b.kind in ("grating", "tracker", "encoders"):
            b.add(got.header.batch_seq, got.columns)

    def collect(self) -> CellStreams:
        args, say = self.args, self.say
        started = time.monotonic()
        last_report = started
        opts = PhaseOptions()
        say(f"collecting {args.key} (connect {args.connect or ['tcp/127.0.0.1:7447']})")
        last_data = None
        while True:
            got = self.receiver.receive(0.2)
            now = time.monotonic()
            if got is not None:
                self._add(got)
                last_data = now
            elif last_data is not None and now - last_data >= args.idle_s:
                say(f"no data for {args.idle_s:g} s: the source stopped, campaign over")
                break
            if args.collect_s and now - started >= args.collect_s:
                say("collection time is up")
                break
            if now - last_report < 5.0:
                continue
            last_report = now
            g = next((b for b in self.builders.values() if b.kind == "grating"), None)
            if g is None or not g._parts["t"]:
                say("waiting for grating samples")
                continue
            gs = g.build()
            ph = find_phases(gs.t_ns, gs.values, opts)
            s = ph.summary()
            n_sweep = sum(sum(v.values()) for v in s["sweep_stops"].values())
            say(
                f"{now - started:.0f} s: {len(gs)} grating samples, {s['dwells']} dwells, "
                f"{n_sweep} sweep stops, {sum(s['home_returns'].values())} Home returns, "
                f"{s['poses']['identify'] + s['poses']['validate']} poses"
            )
            if ph.poses:
                tail = find_dwells(gs.t_ns[-20000:], gs.values[-20000:], opts)
                if tail and tail[-1].i1 >= min(len(gs), 20000) - 2:
                    still_s = tail[-1].duration_s
                    if still_s >= args.idle_s:
                        say(f"the robot has been still for {still_s:.1f} s: campaign over")
                        break
        return pick_streams(self.builders, "live zenoh")

    # -- publication -----------------------------------------------------------------
    def publish(self, run: dict[str, Any], out: Path) -> int:
        from calibration.description import load_robot
        from calibration.kinematics import KinematicModel, flange_poses
        from calibration.model_effects import predict_tcp
        from calibration.scale_files import read_scale_toml
        from daq.bus import JSON_ENCODING, ChannelPublisher, SchemaServer
        from daq.columnar import Column, StreamSchema

        args, say = self.args, self.say
        desc = load_robot(run["calibrated"])
        model = KinematicModel.from_description(desc)
        scale = read_scale_toml(run["files"]["scale"])
        phases = json.loads(Path(run["files"]["phases"]).read_text())
        enc_offset = np.asarray(phases.get("encoder_offset_deg") or [0.0] * desc.n_joints)
        gear = np.array([j.gear_ratio or 100.0 for j in desc.joints], dtype=float)
        cpr = float(phases.get("encoder_counts_per_rev", 131072))
        t0_ns = int(phases.get("campaign", {}).get("t0_ns", 0))
        n = desc.n_joints
        grating = next((b for b in self.builders.values() if b.kind == "grating"), None)
        wait_s = float(getattr(args, "wait_s", 60.0))
        deadline = time.monotonic() + wait_s
        while grating is None:  # no collection (--from): the first grating batch names it
            if time.monotonic() >= deadline:
                raise LiveTwinError(
                    f"no grating samples on {args.key} within {wait_s:g} s "
                    f"(--connect {' '.join(args.connect or ['tcp/127.0.0.1:7447'])}, --wait-s)"
                )
            got = self.receiver.receive(min(1.0, max(0.0, deadline - time.monotonic())))
            if got is not None:
                self._add(got)
                grating = next((b for b in self.builders.values() if b.kind == "grating"), None)
        cell = str(grating.meta.get("cell", "cell"))
        robot = str(grating.meta.get("robot", "robot"))
        keys = twin_keys(cell, robot)
        schema = StreamSchema(
            keys["state"],
            (
                Column("seq", "uint64", (), "", None, "twin sample number"),
                Column("t_mapped_ns", "int64", (), "ns", "host_utc", "grating sample time"),
                Column("t_publish_ns", "int64", (), "ns", "host_utc", "when published"),
                Column("q_deg", "float64", (n,), "deg", None, "joint angles from the gratings"),
                Column("tcp_mm", "float64", (3,), "mm", None, "TCP, tracker frame"),
                Column("flange_mm", "float64", (3,), "mm", None, "flange origin"),
                Column("flange_quat", "float64", (4,), "", None, "flange rotation w, x, y, z"),
                Column(
                    "encoder_minus_grating_deg",
                    "float64",
                    (n,),
                    "deg",
                    None,
                    "motor encoder joint angle minus grating angle (NaN: no encoder)",
                ),
            ),
            {"cell": cell, "robot": robot, "model": str(run["calibrated"]), "source": "twin run"},
        )
        schemas = SchemaServer(self.session, TWIN_PREFIX)
        pub = ChannelPublisher(self.session, schema, schemas=schemas)
        health_pub = self.session.declare_publisher(keys["health"], encoding=JSON_ENCODING)
        say(f"publishing the live twin on {keys['state']} (health: {keys['health']})")
        print(json.dumps({"twin": "live", "keys": keys}), flush=True)
        enc_t = np.empty(0, dtype=np.int64)
        enc_v = np.empty((0, n))
        seq = 0
        lat: list[float] = []
        lat_all: list[float] = []
        period_start = time.monotonic()
        samples_period = 0
        started = time.monotonic()
        joints = np.arange(1, n + 1)
        home = np.array(desc.home, dtype=float)
        while True:
            if args.publish_s and time.monotonic() - started >= args.publish_s:
                break
            # drain what has arrived and evaluate the grating samples in one call: the
            # daemon sends ~1 ms batches, one model evaluation per batch would fall behind
            batch: list[Any] = []
            got = self.receiver.receive(0.1)
            while got is not None and len(batch) < 500:
                batch.append(got)
                got = self.receiver.receive(0.0)
            if got is not None:
                batch.append(got)
            now_m = time.monotonic()
            g_counts, g_t, g_ok = [], [], []
            for got in batch:
                b = self.builders.get(got.key)
                if b is None:
                    b = self.builders[got.key] = StreamBuilder(got.key, got.schema.to_json())
                cols = got.columns
                if b.kind == "encoders":
                    v = np.column_stack([cols[c] for c in b.channels]).astype(float)
                    deg = v / cpr * 360.0 / gear + enc_offset
                    enc_t = np.concatenate((enc_t, cols["t_mapped_ns"]))[-2000:]
                    enc_v = np.concatenate((enc_v, deg))[-2000:]
                elif b.kind == "grating":
                    g_counts.append(np.column_stack([cols[c] for c in b.channels]))
                    g_t.append(np.asarray(cols["t_mapped_ns"], dtype=np.int64))
                    g_ok.append(np.asarray(cols["t_mapped_ok"], dtype=np.uint8))
            if g_counts:
                counts = np.concatenate(g_counts)
                t_map = np.concatenate(g_t)
                settled = np.concatenate(g_ok) == 1
                m = counts.shape[0]
                jj = np.broadcast_to(joints, (m, n))
                angle = scale.angles_deg(jj.ravel(), counts.ravel()).reshape(m, n)
                q = home + angle
                q_rad = np.radians(q)
                tcp = predict_tcp(desc, q_rad, (t_map - t0_ns) * 1e-9)
                fl = flange_poses(model, q_rad)
                diff = np.full((m, n), np.nan)
                if enc_t.size:
                    idx = np.clip(np.searchsorted(enc_t, t_map), 0, enc_t.size - 1)
                    diff = enc_v[idx] - q
                t_pub = time.time_ns()
                pub.publish(
                    {
                        "seq": np.arange(seq, seq + m, dtype=np.uint64),
                        "t_mapped_ns": t_map,
                        "t_publish_ns": np.full(m, t_pub, dtype=np.int64),
                        "q_deg": q,
                        "tcp_mm": tcp,
                        "flange_mm": fl[:, :3, 3],
                        "flange_quat": _quaternions(fl[:, :3, :3]),
                        "encoder_minus_grating_deg": diff,
                    }
                )
                seq += m
                samples_period += m
                # latency on settled clock maps only (provisional mapped times can be off)
                lat.extend(((t_pub - t_map[settled]) * 1e-6).tolist())
                lat_all.extend(((t_pub - t_map) * 1e-6).tolist())
            if now_m - period_start >= 1.0:
                a = np.asarray(lat if lat else lat_all) if (lat or lat_all) else np.zeros(1)
                doc = {
                    "t_host_ns": time.time_ns(),
                    "cell": cell,
                    "robot": robot,
                    "state": "publishing",
                    "rate_hz": samples_period / (now_m - period_start),
                    "samples": seq,
                    "latency_ms": {
                        "p50": float(np.percentile(a, 50)),
                        "p99": float(np.percentile(a, 99)),
                        "max": float(a.max()),
                    },
                    "latency": "publication time minus the grating sample's mapped time",
                    "clock_settled": bool(lat),
                    "model": str(run["calibrated"]),
                }
                health_pub.put(json.dumps(doc))
                say(
                    f"live twin: {doc['rate_hz']:.0f} samples/s, latency p50 "
                    f"{doc['latency_ms']['p50']:.1f} ms, p99 {doc['latency_ms']['p99']:.1f} ms"
                    + ("" if lat else " (clock map not settled yet)")
                )
                period_start, samples_period, lat, lat_all = now_m, 0, [], []
        pub.close()
        health_pub.undeclare()
        schemas.close()
        say(f"published {seq} twin samples")
        return 0

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.receiver.close()
        self.session.close()


def _quaternions(r: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(N, 4)`` (w, x, y, z) of rotation matrices ``(N, 3, 3)``."""
    w = np.sqrt(np.maximum(0.0, 1.0 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2])) / 2
    x = np.sqrt(np.maximum(0.0, 1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2])) / 2
    y = np.sqrt(np.maximum(0.0, 1.0 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2])) / 2
    z = np.sqrt(np.maximum(0.0, 1.0 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2])) / 2
    x = np.copysign(x, r[:, 2, 1] - r[:, 1, 2])
    y = np.copysign(y, r[:, 0, 2] - r[:, 2, 0])
    z = np.copysign(z, r[:, 1, 0] - r[:, 0, 1])
    q = np.column_stack([w, x, y, z])
    return q / np.linalg.norm(q, axis=1, keepdims=True)
