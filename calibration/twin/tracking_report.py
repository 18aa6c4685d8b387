"""``twin track --report``: what the tracker followed, what it gained, and when it changed.

The one-step-ahead error of the static (calibrated) model against the tracked one per
time window; the same checks tracked in a shuffled order (the gain that does not need
time order: neighbouring checks sharing a local residual, not the robot moving); every
step and alarm with its time and size; the parameters over time as a figure.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.twin.step_test import false_alarm_rate
from calibration.twin.tracking import SCALE_SUFFIX, TrackingRun, TrackingSetup

FloatArray = NDArray[np.float64]

#: The report's time windows (s).
WINDOW_S = 3600.0


@dataclass(frozen=True)
class TrackingEvidence:
    """A run with what it is compared against: the static model's errors ``(m,)`` mm and
    the tracker's errors over the same checks in a shuffled order ``(m,)`` mm."""

    setup: TrackingSetup
    run: TrackingRun
    pose: tuple[str, ...]
    t_s: FloatArray  # (m,)
    static_mm: FloatArray  # (m,)
    shuffled_mm: FloatArray  # (m,) in the input's row order


def _stats(err: FloatArray) -> dict[str, float]:
    return {
        "mean_mm": float(np.mean(err)),
        "rms_mm": float(np.sqrt(np.mean(err**2))),
        "max_mm": float(np.max(err)),
    }


def _why(name: str) -> str:
    if name.startswith("base."):
        return "base frame: base creep, a bumped tracker"
    if name.startswith("tool."):
        return "tool: a remounted target"
    if name.endswith(SCALE_SUFFIX):
        return "length scale of the link group: thermal growth"
    return "asked for with --params"


def _events(ev: TrackingEvidence) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Steps (detected row, onset, size) and alarms (each standing span's first row)."""
    run, t = ev.run, ev.t_s
    steps = []
    for detected, onset in run.steps:
        before = run.theta[onset - 1] if onset > 0 else np.zeros(run.theta.shape[1])
        after_rows = [i for i in range(detected, len(t)) if run.states[i] != "step"]
        after = run.theta[after_rows[0] if after_rows else -1]
        moved = ev.setup.reference_jacobian @ (after - before)
        steps.append(
            {
                "detected_pose": ev.pose[detected],
                "detected_t_s": float(t[detected]),
                "onset_pose": ev.pose[onset],
                "onset_t_s": float(t[onset]),
                "checks_to_detect": int(detected - onset + 1),
                "a_priori_error_mm": float(run.error_mm[onset]),
                "tcp_moved_mm": float(np.max(np.linalg.norm(moved, axis=1))),
            }
        )
    alarms = []
    for i, state in enumerate(run.states):
        if state == "alarm" and (i == 0 or run.states[i - 1] != "alarm"):
            alarms.append(
                {
                    "pose": ev.pose[i],
                    "t_s": float(t[i]),
                    "tcp_moved_mm": float(run.displacement_mm[i]),
                }
            )
    return steps, alarms


def build_tracking_report(ev: TrackingEvidence, sources: dict[str, str]) -> dict[str, Any]:
    """The report as a JSON-ready document."""
    run, setup, t = ev.run, ev.setup, ev.t_s
    settings = setup.settings
    windows = []
    edges = np.arange(t[0], t[-1] + WINDOW_S, WINDOW_S)
    for lo in edges[:-1]:
        sel = (t >= lo) & (t < lo + WINDOW_S)
        if sel.any():
            windows.append(
                {
                    "from_s": float(lo),
                    "to_s": float(lo + WINDOW_S),
                    "checks": int(sel.sum()),
                    "static_mean_mm": float(ev.static_mm[sel].mean()),
                    "tracked_mean_mm": float(run.error_mm[sel].mean()),
                    "shuffled_mean_mm": float(ev.shuffled_mm[sel].mean()),
                }
            )
    static, tracked, shuffled = (
        float(np.mean(e)) for e in (ev.static_mm, run.error_mm, ev.shuffled_mm)
    )
    steps, alarms = _events(ev)
    test = settings.step
    final = setup.absolute(run.state.theta)
    return {
        "sources": sources,
        "checks": len(t),
        "span_s": [float(t[0]), float(t[-1])],
        "tracked": [{"name": n, "why": _why(n)} for n in setup.names],
        "errors": {
            "static": _stats(ev.static_mm),
            "tracked": _stats(run.error_mm),
            "shuffled_order": _stats(ev.shuffled_mm),
        },
        "gain": {
            "total_mm": static - tracked,
            "from_following_mm": shuffled - tracked,
            "from_neighbouring_checks_mm": static - shuffled,
        },
        "windows": windows,
        "steps": steps,
        "alarms": alarms,
        "final": {n: float(v) for n, v in zip(setup.names, final, strict=True)},
        "settings": {
            "sigma_mm": setup.sigma_mm,
            "forgetting": asdict(settings.forgetting),
            "prior_weight": settings.prior_weight,
            "step_test": asdict(test),
            "step_false_alarms_per_check": false_alarm_rate(test, 1000, 200),
            "step_false_alarm_simulated_checks": 1000 * 200,
            "alarm_mm": settings.alarm_mm,
        },
    }


def report_markdown(doc: dict[str, Any]) -> str:
    """The report for a person."""
    e, g = doc["errors"], doc["gain"]
    lines = [
        "# Tracking report",
        "",
        f"{doc['checks']} checks from {doc['sources']['data']} on {doc['sources']['model']}.",
        "",
        "## Tracked parameters",
        "",
        *(f"- `{p['name']}`: {p['why']}" for p in doc["tracked"]),
        "",
        "## One-step-ahead error (a priori, mm)",
        "",
        "| model | mean | RMS | max |",
        "|---|---|---|---|",
        *(
            f"| {label} | {e[k]['mean_mm']:.4f} | {e[k]['rms_mm']:.4f} | {e[k]['max_mm']:.4f} |"
            for k, label in (
                ("static", "static (calibrated)"),
                ("tracked", "tracked, time order"),
                ("shuffled_order", "tracked, shuffled order"),
            )
        ),
        "",
        f"Gain {g['total_mm']:+.4f} mm: {g['from_following_mm']:+.4f} mm from following the "
        f"robot in time (shuffled − tracked), {g['from_neighbouring_checks_mm']:+.4f} mm "
        "without time order (static − shuffled: local residuals that neighbouring checks "
        "share, and the run's average change).",
        "",
        "| window (s) | checks | static | tracked | shuffled |",
        "|---|---|---|---|---|",
        *(
            f"| {w['from_s']:.0f}–{w['to_s']:.0f} | {w['checks']} | {w['static_mean_mm']:.4f} "
            f"| {w['tracked_mean_mm']:.4f} | {w['shuffled_mean_mm']:.4f} |"
            for w in doc["windows"]
        ),
        "",
        "## Steps and alarms",
        "",
    ]
    for s in doc["steps"]:
        lines.append(
            f"- step at {s['onset_t_s']:.0f} s (pose {s['onset_pose']}), reported at "
            f"{s['detected_t_s']:.0f} s after {s['checks_to_detect']} check(s): a-priori error "
            f"{s['a_priori_error_mm']:.3f} mm, the TCP moved {s['tcp_moved_mm']:.3f} mm"
        )
    for a in doc["alarms"]:
        lines.append(
            f"- alarm from {a['t_s']:.0f} s (pose {a['pose']}): the TCP moved "
            f"{a['tcp_moved_mm']:.3f} mm at the validation poses"
        )
    if not doc["steps"] and not doc["alarms"]:
        lines.append("none")
    rate = doc["settings"]["step_false_alarms_per_check"]
    n = doc["settings"]["step_false_alarm_simulated_checks"]
    said = f"{rate:.2g} per check" if rate > 0 else f"none (< {1.0 / n:.0e} per check)"
    lines += ["", f"Step test false alarms in {n} simulated checks (χ²₃): {said}.", ""]
    return "\n".join(lines)


def parameter_figure(ev: TrackingEvidence, path: Path) -> None:
    """The tracked parameters' change from the calibrated model over time (mm, µrad, ppm)
    with ±1 σ, and the errors of both models; steps as vertical lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run, names = ev.run, ev.setup.names
    hours = (ev.t_s - ev.t_s[0]) / 3600.0
    fig, axes = plt.subplots(len(names) + 1, 1, figsize=(10, 1.6 * (len(names) + 1)), sharex=True)
    for i, (ax, name) in enumerate(zip(axes[:-1], names, strict=True)):
        unit, factor = ("µrad", 1e6) if name.endswith("_rad") else ("mm", 1.0)
        if name.endswith(SCALE_SUFFIX):
            unit, factor = "ppm", 1e6
        v, s = factor * run.theta[:, i], factor * run.theta_se[:, i]
        ax.fill_between(hours, v - s, v + s, color="#2e5c8a", alpha=0.2, linewidth=0)
        ax.plot(hours, v, color="#2e5c8a", linewidth=1)
        ax.set_ylabel(f"Δ{name}\n{unit}", fontsize=7)
    axes[-1].plot(hours, ev.static_mm, ".", color="#d08770", markersize=3, label="static")
    axes[-1].plot(hours, run.error_mm, ".", color="#2e5c8a", markersize=3, label="tracked")
    axes[-1].set_ylabel("a-priori\nerror mm", fontsize=7)
    axes[-1].set_xlabel("hours since the first check")
    axes[-1].legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
        for detected, _ in run.steps:
            ax.axvline(hours[detected], color="black", linewidth=0.7, linestyle="--")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_tracking_report(directory: Path, doc: dict[str, Any], ev: TrackingEvidence) -> None:
    """report.json, report.md and parameters.png into ``directory`` (staged by the caller)."""
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "report.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    (directory / "report.md").write_text(report_markdown(doc), encoding="utf-8")
    parameter_figure(ev, directory / "parameters.png")
