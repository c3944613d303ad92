"""The Foxglove and PlotJuggler layouts (config/): their files' structure as each tool reads it, and every topic
and diagnostic series they show is one the three nodes publish."""

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

CONFIG = Path(__file__).resolve().parents[1] / "config"


def foxglove_panels(node: object) -> list[str]:
    """The panel ids of a Foxglove mosaic layout tree."""
    if isinstance(node, str):
        return [node]
    assert set(node) >= {"direction", "first", "second"} and node["direction"] in ("row", "column"), node
    assert 0 < node.get("splitPercentage", 50) < 100
    return foxglove_panels(node["first"]) + foxglove_panels(node["second"])


def foxglove_topics() -> set[str]:
    layout = json.loads((CONFIG / "foxglove_layout.json").read_text())
    assert set(layout) >= {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"}
    panels = foxglove_panels(layout["layout"])
    assert sorted(panels) == sorted(layout["configById"]), "every panel in the mosaic is configured, and only those"
    topics = set()
    for panel_id, config in layout["configById"].items():
        kind = panel_id.split("!")[0]
        if kind == "Plot":
            assert config["paths"] and config["xAxisVal"] in ("timestamp", "custom")
            paths = [path["value"] for path in config["paths"]]
            if config["xAxisVal"] == "custom":
                paths.append(config["xAxisPath"]["value"])
            assert all(path.get("timestampMethod") in ("receiveTime", "headerStamp") for path in config["paths"])
            topics |= {value.split(".")[0] for value in paths}
        else:
            assert kind == "DiagnosticSummary"
            topics.add(config["topicToRender"])
    return topics


def check_splitter(element: ET.Element) -> list[ET.Element]:
    """The DockAreas under a PlotJuggler DockSplitter, checking its count and sizes as PlotJuggler restores them."""
    children = list(element)
    sizes = [float(size) for size in element.get("sizes").split(";")]
    assert element.get("orientation") in ("|", "-") and int(element.get("count")) == len(children) == len(sizes)
    assert abs(sum(sizes) - 1.0) < 1e-9
    areas = []
    for child in children:
        assert child.tag in ("DockArea", "DockSplitter")
        areas += [child] if child.tag == "DockArea" else check_splitter(child)
    return areas


def plotjuggler_series() -> set[str]:
    root = ET.parse(CONFIG / "plotjuggler_layout.xml").getroot()
    widget = root.find("tabbed_widget")
    assert root.tag == "root" and widget.get("parent") == "main_window"
    series = set()
    for tab in widget.findall("Tab"):
        containers = tab.findall("Container")
        assert int(tab.get("containers")) == len(containers) >= 1
        for container in containers:
            for area in check_splitter(container.find("DockSplitter")):
                plot = area.find("plot")
                assert area.get("name") and plot.get("mode") in ("TimeSeries", "XYPlot")
                for curve in plot.findall("curve"):
                    if plot.get("mode") == "XYPlot":
                        series |= {curve.get("curve_x"), curve.get("curve_y")}
                    else:
                        series.add(curve.get("name"))
    return series


def test_the_layouts_show_the_stage_the_loop_the_residual_and_the_diagnostics():
    topics = foxglove_topics()
    assert topics == {"/joint_states", "/setpoint", "/current_cmd", "/current_applied", "/identification/residual",
                      "/diagnostics"}
    series = plotjuggler_series()
    assert {"/joint_states/stage_x/position", "/current_applied/data", "/identification/residual/stage_x/position",
            "/setpoint/data"} <= series
    assert any(name.startswith("/diagnostics/") and name.endswith("/level") for name in series)


def test_the_layouts_name_what_the_nodes_publish():
    """The three nodes (started here in a private context, root namespace) publish every topic the layouts
    plot, and PlotJuggler's names for their /diagnostics series (topic/hardware_id/name/key) are the layout's."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.context import Context

    from sma_stage.nodes.compensator_node import CompensatorNode
    from sma_stage.nodes.identification_node import IdentificationNode
    from sma_stage.nodes.stage_node import StageNode

    context = Context()
    rclpy.init(context=context)
    nodes = [node_type(context=context) for node_type in (StageNode, CompensatorNode, IdentificationNode)]
    try:
        topics = {name for node in nodes for name, _ in node.get_publisher_names_and_types_by_node(
            node.get_name(), node.get_namespace())}
        assert foxglove_topics() <= topics | {"/setpoint"}  # the setpoint is the user's, the compensator's input
        stage, compensator, identification = nodes
        from sma_stage.nodes.model_watch import model_message

        identification.on_model_in_force(model_message(compensator.model.to_yaml_text(), compensator.model_source))
        statuses = [stage.diagnostic_status(), compensator.diagnostic_status(),
                    identification.watch.diagnostic_status()]
        available = {f"/diagnostics/{status.hardware_id}/{status.name}/{key}" for status in statuses
                     for key in ["level"] + [value.key for value in status.values]}
        wanted = {name for name in plotjuggler_series() if name.startswith("/diagnostics/")}
        assert wanted and wanted <= available, wanted - available
    finally:
        for node in nodes:
            getattr(node, "close", lambda: None)()
            node.destroy_node()
        context.try_shutdown()
