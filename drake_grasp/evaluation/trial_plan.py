"""The trial plan of a Monte Carlo run: `TrialTask` (one episode, or one whole clutter run
of several attempts, with the experiment settings it carries), `plan_tasks` (the tasks of a
run: trial i of every condition asked, user and extra built-in policies after the
experiment's own, all with trial i's seed), and the experiment and condition a task runs
(`task_experiment`, `task_condition`). What runs the tasks is `drake_grasp.evaluation.
trial_worker`; what drives them is `drake_grasp.evaluation.montecarlo`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from drake_grasp.evaluation.experiments import (EXTRA_POLICIES, Condition, Experiment,
                                     get_experiment, plugin_condition)


@dataclass(frozen=True)
class TrialTask:
    """One unit of work: an episode, or a whole clutter run (several attempts)."""

    experiment: str
    condition: str
    index: int
    base_seed: int
    # A `PHYSICS_PROFILES` name the trial runs with; "" = the scenario's (the default).
    physics_profile: str = ""
    # A user policy's ``MODULE:FACTORY`` (`drake_grasp.policies.plugins`), or a built-in policy of
    # `experiments.EXTRA_POLICIES` the experiment does not list, when `condition` is one
    # (its condition is `experiments.plugin_condition`); "" for the experiment's own.
    policy_spec: str = ""
    # `Experiment.patches`: the settings its condition runs with (weights, options).
    patches: tuple = ()

    @property
    def trial_id(self) -> str:
        return f"{self.experiment}/{self.condition}/{self.index:04d}"


def task_experiment(task: TrialTask) -> Experiment:
    """The experiment a task belongs to, with the settings the task carries (physics
    profile and scenario patches: CNN and GPD weights, the closed-loop options, ...)."""
    experiment = get_experiment(task.experiment)
    if task.physics_profile:
        experiment = dataclasses.replace(experiment, physics_profile=task.physics_profile)
    if task.patches:
        experiment = dataclasses.replace(experiment, patches=tuple(task.patches))
    return experiment


def plan_tasks(experiment: Experiment, *, trials: int | None, seed: int,
               conditions: list[str] | None = None) -> list[TrialTask]:
    """The tasks of a run: trial i of every condition asked (the experiment's order, then
    the user policies, ``MODULE:FACTORY`` entries of `conditions`, and the built-in
    policies of `experiments.EXTRA_POLICIES` that the experiment does not list, in the
    order given), all with trial i's seed."""
    from drake_grasp.policies.plugins import is_policy_spec

    n = experiment.trials if trials is None else int(trials)
    if n < 1:
        raise ValueError(f"--trials: expected >= 1, got {n}")
    names = [c.name for c in experiment.conditions]
    specs = []
    if conditions:
        specs = list(dict.fromkeys(
            c for c in conditions
            if is_policy_spec(c) or (c in EXTRA_POLICIES and c not in names)))
        unknown = [c for c in conditions if c not in names and c not in specs]
        if unknown:
            raise ValueError(f"--conditions: {unknown} not in experiment "
                             f"{experiment.name}; its conditions: {names}, a built-in "
                             f"policy {list(EXTRA_POLICIES)} or a user policy "
                             "MODULE:FACTORY (see drake_grasp.policies.plugins)")
        names = [c for c in names if c in conditions]
    asked = [(c, "") for c in names] + [(plugin_condition(experiment, s).name, s) for s in specs]
    return [TrialTask(experiment.name, c, i, int(seed), experiment.physics_profile, spec,
                      experiment.patches)
            for i in range(n) for c, spec in asked]


def task_condition(task: TrialTask, experiment: Experiment) -> Condition:
    """The condition a task runs: the experiment's, or a user policy's."""
    if task.policy_spec:
        return plugin_condition(experiment, task.policy_spec)
    return _condition(experiment, task.condition)


def _condition(experiment: Experiment, name: str) -> Condition:
    for c in experiment.conditions:
        if c.name == name:
            return c
    raise ValueError(f"experiment {experiment.name}: no condition {name!r}")

