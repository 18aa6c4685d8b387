"""Robot description files: presets, round trips, and errors that name file, table and key."""

from __future__ import annotations

import copy
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import pytest
import tomli_w

from calibration.errors import CalibrationError, DescriptionError
from calibration.model.description import (
    EffectDescription,
    RobotDescription,
    load_robot,
    preset_names,
)

PRESETS = ("kr500", "kr210_r3100", "hp20d")


def preset_document(name: str = "kr500") -> dict[str, Any]:
    text = (resources.files("calibration.presets") / f"{name}.toml").read_text("utf-8")
    return tomllib.loads(text)


def write(tmp_path: Path, doc: dict[str, Any], name: str = "robot.toml") -> Path:
    path = tmp_path / name
    path.write_text(tomli_w.dumps(doc), encoding="utf-8")
    return path


def load_error(path: Path) -> str:
    with pytest.raises(DescriptionError) as info:
        RobotDescription.load(path)
    return str(info.value)


# -- presets and round trips ------------------------------------------------------------
def test_preset_names_lists_the_shipped_robots():
    assert set(PRESETS) <= set(preset_names())


@pytest.mark.parametrize("name", PRESETS)
def test_preset_loads(name):
    desc = load_robot(name)
    assert desc.n_joints == 6
    assert desc.home == (0.0,) * 6
    assert desc.base is not None and desc.tool.z_mm > 0
    assert all(j.lower_deg < j.upper_deg for j in desc.joints)


@pytest.mark.parametrize("name", PRESETS)
def test_round_trip_through_text_and_file(name, tmp_path):
    desc = load_robot(name)
    assert RobotDescription.loads(desc.dumps()) == desc
    path = tmp_path / f"{name}.toml"
    desc.save(path)
    assert RobotDescription.load(path) == desc
    assert load_robot(path) == desc  # by path as well as by preset name
    assert load_robot(str(path)) == desc


def test_round_trip_keeps_effects_and_optional_fields(tmp_path):
    doc = preset_document()
    doc["effect"] = [
        {"kind": "joint_compliance", "stiffness_nmm_per_rad": [5.7e7, 6.2e6, 1.2e7]},
        {"kind": "backlash", "width_rad": 1e-4},
    ]
    doc.pop("home_deg")
    desc = RobotDescription.load(write(tmp_path, doc))
    assert desc.home_deg is None and desc.home == (0.0,) * 6
    assert desc.effects == (
        EffectDescription("joint_compliance", {"stiffness_nmm_per_rad": (5.7e7, 6.2e6, 1.2e7)}),
        EffectDescription("backlash", {"width_rad": 1e-4}),
    )
    assert RobotDescription.loads(desc.dumps()) == desc


def test_defaults_when_tool_and_base_are_omitted(tmp_path):
    doc = preset_document()
    del doc["tool"], doc["base"]
    for joint in doc["joint"]:
        for key in ("gear_ratio", "mass_kg", "com_mm", "beta_deg"):
            joint.pop(key, None)
    desc = RobotDescription.load(write(tmp_path, doc))
    assert desc.base is None and (desc.tool.x_mm, desc.tool.y_mm, desc.tool.z_mm) == (0, 0, 0)
    assert all(j.beta_deg == 0.0 and j.gear_ratio is None for j in desc.joints)
    assert RobotDescription.loads(desc.dumps()) == desc


# -- errors -----------------------------------------------------------------------------
def mutate(doc: dict[str, Any], table: str, key: str, value: Any, index: int = 1) -> None:
    target = doc[table][index] if table == "joint" else doc if table == "top" else doc[table]
    if value is _DELETE:
        del target[key]
    else:
        target[key] = value


_DELETE = object()

# (table, key, value, expected fragments of the message besides the file name)
BAD_VALUES = [
    ("joint", "a_mm", _DELETE, ["[[joint]] #2", "key 'a_mm'", "missing"]),
    ("joint", "lower_deg", _DELETE, ["[[joint]] #2", "key 'lower_deg'", "missing"]),
    ("joint", "twist_deg", 1.0, ["[[joint]] #2", "key 'twist_deg'", "unknown key"]),
    ("joint", "a_mm", float("nan"), ["[[joint]] #2", "key 'a_mm'", "finite"]),
    ("joint", "d_mm", float("inf"), ["[[joint]] #2", "key 'd_mm'", "finite"]),
    ("joint", "a_mm", "500", ["[[joint]] #2", "key 'a_mm'", "expected a number, got str"]),
    ("joint", "alpha_deg", True, ["[[joint]] #2", "key 'alpha_deg'", "got bool"]),
    ("joint", "upper_deg", -40.0, ["[[joint]] #2", "key 'upper_deg'", "must exceed"]),
    ("joint", "upper_deg", -50.0, ["[[joint]] #2", "key 'upper_deg'", "must exceed"]),
    ("joint", "com_mm", [1.0, 2.0], ["[[joint]] #2", "key 'com_mm'", "expected 3 numbers"]),
    ("joint", "gear_ratio", 0, ["[[joint]] #2", "key 'gear_ratio'", "zero"]),
    ("joint", "mass_kg", -1.0, ["[[joint]] #2", "key 'mass_kg'", "negative"]),
    ("top", "home_deg", [0.0] * 5, ["top level", "key 'home_deg'", "expected 6 numbers"]),
    ("top", "home_deg", [0.0, 200.0, 0, 0, 0, 0], ["key 'home_deg'", "joint 2", "outside"]),
    ("top", "home_deg", "zero", ["key 'home_deg'", "expected an array"]),
    ("top", "colour", "orange", ["top level", "key 'colour'", "unknown key"]),
    ("top", "name", _DELETE, ["top level", "key 'name'", "missing"]),
    ("top", "name", 5, ["top level", "key 'name'", "non-empty string"]),
    ("top", "joint", _DELETE, ["top level", "key 'joint'", "[[joint]]"]),
    ("top", "joint", [], ["top level", "key 'joint'", "[[joint]]"]),
    ("tool", "z_mm", _DELETE, ["[tool]", "key 'z_mm'", "missing"]),
    ("tool", "z_mm", "180", ["[tool]", "key 'z_mm'", "expected a number"]),
    ("tool", "w_mm", 1.0, ["[tool]", "key 'w_mm'", "unknown key"]),
    ("base", "rz_deg", _DELETE, ["[base]", "key 'rz_deg'", "missing"]),
    ("base", "rz_deg", float("-inf"), ["[base]", "key 'rz_deg'", "finite"]),
    ("base", "x_mm", False, ["[base]", "key 'x_mm'", "got bool"]),
]


@pytest.mark.parametrize(
    ("table", "key", "value", "fragments"),
    BAD_VALUES,
    ids=[f"{t}.{k}={'<deleted>' if v is _DELETE else v!r}" for t, k, v, _ in BAD_VALUES],
)
def test_bad_values_are_reported_with_file_table_and_key(tmp_path, table, key, value, fragments):
    doc = copy.deepcopy(preset_document())
    mutate(doc, table, key, value)
    path = write(tmp_path, doc)
    message = load_error(path)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message, message


def test_joint_that_is_not_a_table(tmp_path):
    path = tmp_path / "robot.toml"
    path.write_text('name = "x"\njoint = [1, 2]\n', encoding="utf-8")
    message = load_error(path)
    assert "[[joint]] #1" in message and "expected a table" in message


def test_invalid_toml_names_the_file(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text('name = "x"\n[[joint]\na_mm = 1\n', encoding="utf-8")
    message = load_error(path)
    assert str(path) in message and "not valid TOML" in message


def test_unreadable_file_names_the_file(tmp_path):
    message = load_error(tmp_path / "absent.toml")
    assert "absent.toml" in message and "cannot read" in message


def test_loads_uses_the_given_source_name():
    with pytest.raises(DescriptionError, match=r"^cell-3: not valid TOML"):
        RobotDescription.loads("= 1", source="cell-3")


def test_unknown_preset_lists_the_presets():
    with pytest.raises(DescriptionError) as info:
        load_robot("kr1000_titan")
    message = str(info.value)
    assert "kr1000_titan" in message and "no preset" in message
    for name in PRESETS:
        assert name in message


def test_description_error_is_a_calibration_and_value_error():
    assert issubclass(DescriptionError, CalibrationError)
    assert issubclass(DescriptionError, ValueError)


@pytest.mark.parametrize(
    ("effect", "fragments"),
    [
        ({"width_rad": 1e-4}, ["[[effect]] #1", "key 'kind'", "missing"]),
        ({"kind": "backlash", "width_rad": {"a": 1}}, ["[[effect]] #1", "key 'width_rad'"]),
        ({"kind": "backlash", "widths_rad": [1e-4, "x"]}, ["[[effect]] #1", "key 'widths_rad'"]),
    ],
)
def test_bad_effects_are_reported(tmp_path, effect, fragments):
    doc = preset_document()
    doc["effect"] = [effect]
    message = load_error(write(tmp_path, doc))
    for fragment in fragments:
        assert fragment in message, message
