"""Pictures of the Diagram: Graphviz text, rendered to SVG/PNG when `dot` is installed."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from drake_grasp.config.scenario import Scenario


def diagram_dot(scenario: Scenario, *, depth: int = 2) -> str:
    """Graphviz text of the episode Diagram for a scenario (its settled scene)."""
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.objects import load_library
    from drake_grasp.world.scene import scenario_scene

    library = load_library(scenario.objects_dir or None)
    # Settled: the start pose is raised above standing objects, and an unsettled pile
    # stacked in the air would put it out of reach.
    scene = scenario_scene(scenario, library)
    diagram = build_episode_diagram(scenario, scene, library).diagram
    return diagram.GetGraphvizString(max_depth=depth)


def write_diagram(scenario: Scenario, *, out: str | Path, depth: int = 2) -> Path:
    """Writes the Diagram to `out`: SVG/PNG through `dot` if available, else `.dot` text.

    Returns the path written (its suffix is `.dot` when `dot` is missing).
    """
    out = Path(out)
    dot_text = diagram_dot(scenario, depth=depth)
    out.parent.mkdir(parents=True, exist_ok=True)
    fmt = out.suffix.lstrip(".").lower()
    dot = shutil.which("dot")
    if fmt in ("svg", "png", "pdf") and dot is not None:
        tmp = out.with_name(out.name + ".tmp")
        subprocess.run([dot, f"-T{fmt}", "-o", str(tmp)], input=dot_text.encode(), check=True)
        tmp.replace(out)
        return out
    target = out if fmt == "dot" else out.with_suffix(".dot")
    tmp = target.with_name(target.name + ".tmp")
    tmp.write_text(dot_text)
    tmp.replace(target)
    return target
