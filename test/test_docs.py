"""The README's parameter tables and the config files agree with what the nodes declare: every parameter
listed, with its default, its range and whether it is read-only."""

import re
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from sma_stage.nodes.compensator_node import COMPENSATOR_PARAMS  # noqa: E402
from sma_stage.nodes.identification_node import IDENTIFICATION_PARAMS  # noqa: E402
from sma_stage.nodes.stage_node import STAGE_PARAMS  # noqa: E402

README = Path(__file__).resolve().parents[1] / "README.md"
DECLARED = {"stage": STAGE_PARAMS, "compensator": COMPENSATOR_PARAMS, "identification": IDENTIFICATION_PARAMS}


def readme_rows(node: str) -> list[list[str]]:
    """The cells of each row of the README's parameter table for node."""
    text = README.read_text()
    start = text.index(f"| `{node}` | default | range | meaning |")
    rows = []
    for line in text[start:].splitlines()[2:]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip().strip("|").split("|", 3)])
    return rows


def documented(node: str) -> dict[str, tuple[str, str, bool]]:
    """name -> (default cell, range cell, read-only) for every parameter the README lists for node."""
    found = {}
    for names_cell, default_cell, range_cell, meaning in readme_rows(node):
        names = re.findall(r"`([^`]+)`", names_cell)
        defaults = default_cell.split(", ")
        ranges = [range_cell] * len(names) if "," not in range_cell else range_cell.split(", ")
        assert len(defaults) == len(names) == len(ranges), names_cell
        for name, default, allowed in zip(names, defaults, ranges, strict=True):
            found[name] = (default, allowed, meaning.startswith("ro;") or meaning == "ro")
    return found


def as_cell(value: object) -> str:
    """How the README writes a default."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f"`{value}`" if value else '`""`'
    return repr(value)


def same_number(cell: str, value: float) -> bool:
    return float(cell) == float(value)


@pytest.mark.parametrize("node", sorted(DECLARED))
def test_readme_parameter_table_matches_the_declarations(node):
    table = documented(node)
    declared = {param.name: param for param in DECLARED[node]}
    assert set(table) == set(declared), "README lists exactly the declared parameters"
    for name, param in declared.items():
        default, allowed, read_only = table[name]
        if isinstance(param.default, (int, float)) and not isinstance(param.default, bool):
            assert same_number(default, param.default), (name, default, param.default)
        else:
            assert default == as_cell(param.default), (name, default, param.default)
        if param.low is None:
            assert allowed == "", f"{name}: the README gives a range the node does not declare"
        else:
            found = re.fullmatch(r"([0-9.e+]+)-([0-9.e+]+)|(-?[0-9.e+-]+) to (-?[0-9.e+-]+)", allowed)
            assert found, f"{name}: no range in the README (declared {param.low} to {param.high})"
            low, high = (group for group in found.groups() if group is not None)
            assert same_number(low, param.low) and same_number(high, param.high), (name, allowed, param.low, param.high)
        assert read_only == param.read_only, f"{name}: read-only {param.read_only}"


@pytest.mark.parametrize("node", sorted(DECLARED))
def test_config_file_values_are_the_declared_defaults(node):
    """config/<node>.yaml documents the defaults: each value there is the one the node declares."""
    import yaml

    (section,) = yaml.safe_load((README.parent / "config" / f"{node}.yaml").read_text()).values()
    values = section["ros__parameters"]
    assert {name: values[name] for name in values} == {param.name: param.default for param in DECLARED[node]
                                                       if param.name in values}
