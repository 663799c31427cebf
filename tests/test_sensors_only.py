"""Sensors only: no privileged station output reaches a policy-side system.

For every built-in sensor policy and for a user plugin, the episode Diagram is built and its
connections read: a station output named in `PRIVILEGED_PORTS` (true poses, contact results,
plant state, the scene graph's query object, the label image, raw renderer images) may feed
the judge alone. The label image reaches the controller only in target mode, which the
scenario (and so every trial record) names.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from drake_grasp.config.policy_spec import PRIVILEGED_PORTS
from drake_grasp.config.scenario import load_scenario
from drake_grasp.policies.decisions import SENSOR_POLICIES

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
PLUGIN = "centroid_policy:make_policy"


def _privileged_feeds(diagram) -> set[tuple[str, str]]:
    """(reading system, station output) for every privileged station output connected."""
    station = diagram.GetSubsystemByName("station")
    out = set()
    for (dst, _), (src, j) in diagram.connection_map().items():
        name = src.get_output_port(j).get_name()
        if src is station and name in PRIVILEGED_PORTS:
            out.add((dst.get_name(), name))
    return out


def _episode(policy: str, library, *, extra: str = ""):
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.world.scene import make_scene

    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        f"{{seed: 0, policy: {policy!r}, scene: {{object_ids: [can_000], pose: lying}}{extra}}}"))
    scene = make_scene(scenario.scene, scenario.seed, library, physics=scenario.physics)
    # A stand-in detector for the gpd policies: the wiring is under test, not the classifier.
    detect = (lambda depth, X_WC: None) if policy.startswith("gpd") else None
    return build_episode_diagram(scenario, scene, library, detect_fn=detect)


@pytest.mark.parametrize("policy", SENSOR_POLICIES + (PLUGIN,))
def test_only_the_judge_reads_privileged_station_outputs(policy, library, monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLES))
    try:
        ed = _episode(policy, library)
    finally:
        sys.modules.pop("centroid_policy", None)
    feeds = _privileged_feeds(ed.diagram)
    readers = {reader for reader, _ in feeds}
    assert readers == {"judge"}, sorted(feeds)
    # the check sees the judge's own feeds, so it would see a policy's
    assert ("judge", "contact_results") in feeds and ("judge", "body_poses") in feeds


def test_label_image_reaches_the_controller_in_target_mode_only(library):
    ed = _episode("ctr", library, extra=", target: can_000")
    readers = {reader for reader, port in _privileged_feeds(ed.diagram) if port == "label_image"}
    # directly, or through the frame buffer of a scenario with sensor timing
    assert readers and readers <= {"controller", "label_image_frames"}, readers
    assert ed.policy.get_name() == "controller"
