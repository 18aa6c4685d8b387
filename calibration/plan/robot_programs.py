"""A planned campaign as robot programs: KUKA KRL (``.src`` + ``.dat``) and ABB RAPID (``.mod``).

Both move joint-interpolated to each pose in travel order and wait there for the tracker:

* **KRL**: each pose an ``E6AXIS`` in the ``.dat`` (``A1..A6`` in the controller's
  degrees, external axes ``E1..E6`` 0), moved to by ``PTP`` with exact stop (no ``C_PTP``:
  the zone is none), at ``$VEL_AXIS[i]`` = the stated percentage of each axis's top
  speed, ``$ACC_AXIS[i]`` 50 %; then ``WAIT SEC`` the dwell.
* **RAPID**: each pose a ``CONST jointtarget`` (``robax`` in the controller's degrees,
  ``extax`` 9E9: none), moved to by ``MoveAbsJ`` with the stated ``speeddata`` and the
  ``fine`` zone (exact stop), then ``WaitTime`` the dwell.

Joint angles are the controller's: ``controller_sign · q + controller_offset_deg`` per
joint (description keys, :class:`calibration.model.description.JointDescription`). A pose
whose direct move from the previous one is not clear of the cell goes through Home
first. Angles are written with :data:`DECIMALS` decimals; :func:`read_krl` and
:func:`read_rapid` parse the files back (in the description's angles).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import ProgramError
from calibration.model.description import RobotDescription

FloatArray = NDArray[np.float64]

#: Decimals of every joint angle written (deg): 1e-5° moves a 3 m arm's TCP 0.5 µm.
DECIMALS = 5


@dataclass(frozen=True)
class ProgramSettings:
    """How the programs move: KRL axis speed in % of the top speed, RAPID speeddata name,
    the dwell at each pose (s) for the tracker to measure."""

    name: str = "twin_plan"
    krl_velocity_pct: int = 20
    rapid_speed: str = "v200"
    dwell_s: float = 3.0
    #: what the poses are, in the programs' first comment
    content: str = "poses in travel order"


def controller_angles_deg(description: RobotDescription, q_deg: ArrayLike) -> FloatArray:
    """The controller's angles ``(N, n)`` deg of the description's ``q_deg`` ``(N, n)``."""
    sign = np.array([j.controller_sign for j in description.joints], dtype=float)
    offset = np.array([j.controller_offset_deg for j in description.joints])
    out: FloatArray = np.asarray(q_deg, dtype=float) * sign + offset
    return out


def description_angles_deg(description: RobotDescription, a_deg: ArrayLike) -> FloatArray:
    """The inverse of :func:`controller_angles_deg`."""
    sign = np.array([j.controller_sign for j in description.joints], dtype=float)
    offset = np.array([j.controller_offset_deg for j in description.joints])
    out: FloatArray = (np.asarray(a_deg, dtype=float) - offset) * sign
    return out


def format_angle(v: float) -> str:
    """An angle (deg) with :data:`DECIMALS` decimals, never ``-0.00000``."""
    text = f"{v:.{DECIMALS}f}"
    return "0." + "0" * DECIMALS if text == "-0." + "0" * DECIMALS else text


def programs_refused(description: RobotDescription) -> str | None:
    """Why no KRL or RAPID program is written for ``description`` (None: they are). Both
    are for the vendors' 6-axis arms (``E6AXIS`` A1..A6, ``robax`` rax_1..rax_6); an arm
    of another count is not programmed in either, and its joints are in the CSV files."""
    if description.n_joints == 6:
        return None
    return (
        f"KRL and RAPID programs are written for 6-axis arms, {description.name!r} has "
        f"{description.n_joints} joints"
    )


def _check(description: RobotDescription) -> None:
    refused = programs_refused(description)
    if refused is not None:
        raise ProgramError(refused)


def krl_program(
    description: RobotDescription,
    q_deg: ArrayLike,
    labels: list[str],
    via_home: set[int],
    settings: ProgramSettings = ProgramSettings(),
) -> tuple[str, str]:
    """The ``.src`` and ``.dat`` texts for poses ``q_deg`` ``(N, 6)`` (description
    angles) named ``labels``; a pose whose index is in ``via_home`` is reached via Home."""
    _check(description)
    a = controller_angles_deg(description, q_deg)
    home = controller_angles_deg(description, np.array([description.home]))[0]
    name = settings.name
    dat = ["&ACCESS RVP", "&REL 1", f"DEFDAT {name}"]
    dat.append(f"  DECL E6AXIS XHOME={_e6axis(home)}")
    for label, row in zip(labels, a, strict=True):
        dat.append(f"  DECL E6AXIS X{label}={_e6axis(row)}")
    dat.append("ENDDAT")
    src = ["&ACCESS RVP", "&REL 1", f"DEF {name}( )"]
    src.append(f"  ; twin plan: {len(labels)} {settings.content}; exact stop at each")
    src.append("  INT I")
    src.append("  BAS (#INITMOV,0)")
    src.append("  FOR I=1 TO 6")
    src.append(f"    $VEL_AXIS[I]={settings.krl_velocity_pct}")
    src.append("    $ACC_AXIS[I]=50")
    src.append("  ENDFOR")
    src.append("  PTP XHOME")
    for i, label in enumerate(labels):
        if i in via_home:
            src.append("  PTP XHOME ; the direct move is not clear of the cell")
        src.append(f"  PTP X{label}")
        src.append(f"  WAIT SEC {settings.dwell_s:g}")
    src.append("  PTP XHOME")
    src.append("END")
    return "\n".join(src) + "\n", "\n".join(dat) + "\n"


def _e6axis(row: FloatArray) -> str:
    axes = ",".join(f"A{i + 1} {format_angle(v)}" for i, v in enumerate(row))
    ext = ",".join(f"E{i} 0.0" for i in range(1, 7))
    return "{" + axes + "," + ext + "}"


def rapid_module(
    description: RobotDescription,
    q_deg: ArrayLike,
    labels: list[str],
    via_home: set[int],
    settings: ProgramSettings = ProgramSettings(),
) -> str:
    """The ``.mod`` text (one module, ``PROC main()``) for the poses (as :func:`krl_program`)."""
    _check(description)
    a = controller_angles_deg(description, q_deg)
    home = controller_angles_deg(description, np.array([description.home]))[0]
    lines = [f"MODULE {settings.name}", f"  ! twin plan: {len(labels)} {settings.content}"]
    lines.append(f"  CONST jointtarget jHome:={_jointtarget(home)};")
    for label, row in zip(labels, a, strict=True):
        lines.append(f"  CONST jointtarget j{label}:={_jointtarget(row)};")
    move = f", {settings.rapid_speed}, fine, tool0;"
    lines += ["  PROC main()", f"    MoveAbsJ jHome{move}"]
    for i, label in enumerate(labels):
        if i in via_home:
            lines.append(f"    MoveAbsJ jHome{move} ! the direct move is not clear of the cell")
        lines.append(f"    MoveAbsJ j{label}{move}")
        lines.append(f"    WaitTime {settings.dwell_s:g};")
    lines += [f"    MoveAbsJ jHome{move}", "  ENDPROC", "ENDMODULE"]
    return "\n".join(lines) + "\n"


def _jointtarget(row: FloatArray) -> str:
    return "[[" + ",".join(format_angle(v) for v in row) + "],[9E9,9E9,9E9,9E9,9E9,9E9]]"


_NUM = r"[-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?"


def read_krl(description: RobotDescription, src: str, dat: str) -> tuple[list[str], FloatArray]:
    """The poses a KRL program moves to, in order (Home excluded): their names and angles
    ``(N, 6)`` in the description's degrees."""
    points: dict[str, list[float]] = {}
    for m in re.finditer(r"DECL\s+E6AXIS\s+(\w+)\s*=\s*\{([^}]*)\}", dat):
        axes = dict(re.findall(rf"\b(A[1-6])\s+({_NUM})", m.group(2)))
        points[m.group(1)] = [float(axes[f"A{i}"]) for i in range(1, 7)]
    names = [n for n in re.findall(r"^\s*PTP\s+(\w+)", src, flags=re.M) if n != "XHOME"]
    missing = [n for n in names if n not in points]
    if missing:
        raise ProgramError(f"KRL: PTP {missing[0]} has no E6AXIS in the .dat")
    a = np.array([points[n] for n in names]).reshape(-1, 6)
    return [n[1:] for n in names], description_angles_deg(description, a)


def read_rapid(description: RobotDescription, mod: str) -> tuple[list[str], FloatArray]:
    """The poses a RAPID module moves to, in order (Home excluded), as :func:`read_krl`."""
    points: dict[str, list[float]] = {}
    for m in re.finditer(r"CONST\s+jointtarget\s+(\w+)\s*:=\s*\[\[([^\]]*)\]", mod):
        points[m.group(1)] = [float(v) for v in m.group(2).split(",")]
    names = [n for n in re.findall(r"MoveAbsJ\s+(\w+)", mod) if n != "jHome"]
    missing = [n for n in names if n not in points]
    if missing:
        raise ProgramError(f"RAPID: MoveAbsJ {missing[0]} has no jointtarget")
    a = np.array([points[n] for n in names]).reshape(-1, 6)
    return [n[1:] for n in names], description_angles_deg(description, a)
