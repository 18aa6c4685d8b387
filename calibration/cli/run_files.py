"""The files of ``twin export`` and ``twin run``, at the command line's edge.

:func:`write_campaign_files` writes a :class:`~calibration.twin.run_documents.CampaignExport`
(``home.csv``, ``sweep.csv``, ``scale.toml``, ``campaign.csv``, ``phases.json``);
:func:`write_twin_run` writes a :class:`~calibration.twin.twin_run.TwinRun` (those, and
``calibrated.toml``, ``report/``, ``scale-report/``, ``run.json``; docs/twin-run.md,
"Outputs"). Both write into the directory they are given, the staging directory of an
:class:`~edges.outputs.OutputSet`. :func:`resolve_run_path` finds the files an earlier
run.json names. Only the command line (``cli.export``, ``cli.run``) and tests import this.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from calibration.identify.campaign_files import write_campaign
from calibration.scales.scale_files import write_csv, write_scale_toml
from calibration.twin.campaign_measurement import Say, quiet
from calibration.twin.run_documents import (
    CALIBRATED_FILE,
    CAMPAIGN_FILES,
    CampaignExport,
    home_table,
    sweep_table,
)
from calibration.twin.twin_run import TwinRun

#: run.json's ``paths_relative_to``: its paths are relative to its own directory
RUN_PATHS_RELATIVE_TO = "run.json"


def write_campaign_files(dest: Path, export: CampaignExport) -> dict[str, Path]:
    """home.csv, sweep.csv, scale.toml, campaign.csv and phases.json into ``dest``; their
    paths by key (:data:`~calibration.twin.run_documents.CAMPAIGN_FILES`)."""
    dest.mkdir(parents=True, exist_ok=True)
    files = {key: dest / name for key, name in CAMPAIGN_FILES.items()}
    write_csv(files["home"], *home_table(export.measurements))
    write_csv(files["sweep"], *sweep_table(export.measurements))
    write_scale_toml(files["scale"], export.scale_document)
    write_campaign(files["campaign"], export.campaign)
    files["phases"].write_text(json.dumps(export.phases, indent=2) + "\n", encoding="utf-8")
    return files


def _without_timings(obj: Any) -> Any:
    """``obj`` without the run's own timings (keys ``elapsed_s``)."""
    if isinstance(obj, dict):
        return {k: _without_timings(v) for k, v in obj.items() if k != "elapsed_s"}
    if isinstance(obj, list):
        return [_without_timings(v) for v in obj]
    return obj


def _write_reports(dest: Path, run: TwinRun, *, figures: bool, say: Say) -> Path:
    """report/ (report.json without the solver times; with ``figures``, report.md and the
    figures too) and, with ``figures``, scale-report/; the report directory."""
    from calibration.effects.report_rendering import write_report
    from calibration.scales.scale_report import write_report as write_scale_report

    report_dir = dest / "report"
    if figures:
        say("writing the report (figures)")
        loop = run.calibration.final.loop
        write_report(report_dir, run.report, list(run.errors), closed_loop=loop)
        write_scale_report(
            run.export.scales,
            dest / "scale-report",
            robot=run.robot.name,
            metadata={"source": "twin run"},
        )
    report_dir.mkdir(parents=True, exist_ok=True)
    (report_dir / "report.json").write_text(
        json.dumps(_without_timings(run.report), indent=2, allow_nan=False) + "\n",
        encoding="utf-8",
    )
    return report_dir


def _run_document(
    run: TwinRun, total_s: float, calibrated: str, report: str, files: dict[str, str]
) -> dict[str, Any]:
    return {
        "calibrated": calibrated,
        "report": report,
        "files": files,
        "stage_table": run.stage_table,
        "joint_fit_rounds": len(run.calibration.rounds),
        "export_s": round(run.export_s, 3),
        "total_s": round(total_s, 3),
        "success": run.success,
    }


def write_twin_run(
    dest: Path,
    out: Path,
    run: TwinRun,
    *,
    report: bool = True,
    say: Say = quiet,
) -> dict[str, Any]:
    """Every file of ``twin run`` into ``dest`` (``report``: with report.md, the figures
    and scale-report/), run.json last; run.json's document with its paths named as under
    ``out``, where ``dest`` is moved to (the stored run.json names them relative to its
    own directory, so that ``twin run --from DIR`` finds them from any working directory).
    ``total_s``: the run's time and the writing's."""
    started = time.perf_counter()
    files = write_campaign_files(dest, run.export)
    calibrated = dest / CALIBRATED_FILE
    run.calibrated.save(calibrated)
    report_dir = _write_reports(dest, run, figures=report, say=say)
    total_s = run.elapsed_s + (time.perf_counter() - started)

    def named(path: Path) -> str:
        return str(out / path.relative_to(dest))

    def beside(path: Path) -> str:
        return path.relative_to(dest).as_posix()

    stored = _run_document(
        run,
        total_s,
        beside(calibrated),
        beside(report_dir),
        {k: beside(v) for k, v in files.items()},
    )
    stored["paths_relative_to"] = RUN_PATHS_RELATIVE_TO
    (dest / "run.json").write_text(json.dumps(stored, indent=2) + "\n", encoding="utf-8")
    return _run_document(
        run, total_s, named(calibrated), named(report_dir), {k: named(v) for k, v in files.items()}
    )


def resolve_run_path(run_dir: str | Path, name: str, relative_to_run: bool) -> Path:
    """Where a path named in ``run_dir/run.json`` is, from this process's working directory.

    run.json written since ``paths_relative_to = "run.json"`` names its files relative to
    its own directory. An older one named them relative to the working directory of the
    run that wrote it: such a path is taken as it is if it exists from here, else found
    beside run.json by its longest tail that exists there (``demo-out/twin/scale.toml``
    from elsewhere: ``<run_dir>/scale.toml``); else the path is returned as written (the
    caller says it is missing)."""
    path = Path(name)
    run_dir = Path(run_dir)
    if path.is_absolute():
        return path
    if relative_to_run:
        return run_dir / path
    if path.exists():
        return path
    parts = path.parts
    for k in range(len(parts)):
        candidate = run_dir.joinpath(*parts[k:])
        if candidate.exists():
            return candidate
    return path
