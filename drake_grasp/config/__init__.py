"""Typed configuration: the `Scenario` and its nested configs, loaded from the
named `*.scenarios.yaml` with unknown keys as errors (`scenario`; its typed sections in
`sections`, the allowed values of each key in `scenario_checks`), contact-simulation
settings beyond Drake's (`physics`), and the harness's policy contract (`policy_spec`).

Floor 5: imports the floors below.
"""
