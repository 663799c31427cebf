"""Typed configuration: the `Scenario` and its nested configs, loaded from the
named `*.scenarios.yaml` with unknown keys as errors (`scenario`), contact-simulation
settings beyond Drake's (`physics`), and the harness's policy contract (`policy_spec`).

Floor 5: imports the floors below.
"""
