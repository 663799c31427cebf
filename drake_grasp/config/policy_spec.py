"""The harness's side of the policy contract: how a scenario names a user policy
(``MODULE:FACTORY``) and the ports a policy system may and may not use.

`drake_grasp.policies.plugins` loads and checks user policies against it; the scenario
loader and the grasp-motion monitor need only these names, so they live on this floor.
"""

from __future__ import annotations

import re

# A spec: dotted module name, ":", dotted attribute path (ASCII identifiers).
_IDENT = r"[A-Za-z_][A-Za-z0-9_]*"
SPEC_RE = re.compile(rf"^(?P<module>{_IDENT}(?:\.{_IDENT})*):(?P<factory>{_IDENT}(?:\.{_IDENT})*)$")

# Closing the gripper on the grasp: a commanded width at or below this [m].
CLOSE_WIDTH_M = 0.001

# Input ports the harness provides (by name), and what each must be.
INPUT_PORTS = ("depth_image", "gpd_depth_image", "gripper_state", "motion_status",
               "X_WG_start", "X_GC")
REQUIRED_OUTPUTS = ("X_WG_desired", "gripper_command")
OPTIONAL_OUTPUTS = ("descending",)
# Station outputs a policy must not read (the judge's, or noise-free truth).
PRIVILEGED_PORTS = ("body_poses", "label_image", "contact_results", "plant_state",
                    "arm_state", "query_object", "depth_image_raw", "gpd_depth_image_raw",
                    "control_status")

_EXPECTED = ("expected MODULE:FACTORY, where MODULE is a module importable from sys.path "
             "or a MODULE.py in the current folder, and FACTORY(scenario) returns a "
             "pydrake LeafSystem (see drake_grasp.policies.plugins)")


def is_policy_spec(policy: str) -> bool:
    """Whether `policy` names a user policy (``MODULE:FACTORY``) rather than a built-in."""
    return isinstance(policy, str) and ":" in policy


def parse_policy_spec(spec: str) -> tuple[str, str]:
    """(module, factory) of a ``MODULE:FACTORY`` spec.

    Raises:
        ValueError: the spec is not of that form; the message names it.
    """
    m = SPEC_RE.match(spec) if isinstance(spec, str) else None
    if m is None:
        raise ValueError(f"policy {spec!r}: not a valid user policy spec; {_EXPECTED}, "
                         "both ASCII identifiers (dotted paths allowed), e.g. "
                         "'centroid_policy:make_policy'")
    return m.group("module"), m.group("factory")
