"""The identity of a Monte Carlo run and the folder it goes to. `run_identity` is what
run.json records (experiment, base seed, object library and its content hash, every
condition's resolved scenario without the per-trial seed and its `config_hash`, the CNN and
GPD weights' checksums, the code tree), `plugin_identity` adds a user policy's code, and
`folder_conflict` / `choose_folder` decide whether a folder can take a run's trials (naming
the first differing key) or, with `force_new`, which `OUT-2`, `OUT-3`, ... next to it does.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from pathlib import Path

from drake_grasp.evaluation.experiments import (CNN_POLICIES, EXTRA_POLICIES, Condition, Experiment,
                                     condition_scenario, plugin_condition)
from drake_grasp.core.provenance import code_tree, file_sha256
from drake_grasp.policies.decisions import GPD_POLICIES


_SEED_LINE = re.compile(r"^seed:[^\n]*$", re.MULTILINE)


def config_hash(scenario_yaml: str) -> str:
    """First 16 hex digits of the SHA-256 of a scenario's YAML with its top-level `seed`
    set to 0.

    The seed is per trial (and per clutter attempt); leaving it out makes the hash name
    the settings under test. Records carry the hash of their condition's shared scenario
    (`experiments.condition_scenario`), so all trials of a condition share one hash, also
    in experiments that choose the object and pose per trial.
    """
    normalised = _SEED_LINE.sub("seed: 0", scenario_yaml, count=1)
    return hashlib.sha256(normalised.encode()).hexdigest()[:16]


def weights_path(scenario) -> str | None:
    """The CNN weights file a scenario's policy loads (comma-separated files for an
    ensemble, `evaluator.weights_files`), None for policies without the CNN."""
    if scenario.policy not in CNN_POLICIES:
        return None
    from drake_grasp.policies.evaluator import weights_files

    return ",".join(weights_files(scenario.controller.weights))


def gpd_weights_path(scenario) -> str | None:
    """The GPD classifier weights file a scenario's policy loads (`gpd.weights`, "" = the
    shipped file), None for policies without it."""
    if scenario.policy not in GPD_POLICIES:
        return None
    from drake_grasp.policies.gpd import default_weights_path

    return scenario.gpd.weights or str(default_weights_path())


def condition_identity(experiment: Experiment, condition: Condition, *,
                       objects_dir: str | None = None) -> dict:
    """What run.json records of one condition, and what a resume compares: the condition's
    fields, its resolved scenario without the per-trial seed (`condition_scenario`), the
    sha256 of the CNN weights file it uses and of the GPD classifier weights file (each
    None when its policy uses none) and its config hash."""
    from pydrake.common.yaml import yaml_load_data

    from drake_grasp.config.scenario import dump_scenario
    from drake_grasp.policies.evaluator import weights_files

    scenario = condition_scenario(experiment, condition, objects_dir=objects_dir)
    yaml = dump_scenario(scenario)
    resolved = yaml_load_data(yaml)
    resolved.pop("seed", None)
    weights = weights_path(scenario)
    gpd_weights = gpd_weights_path(scenario)
    return {**dataclasses.asdict(condition), "scenario": resolved,
            "weights_sha256": None if weights is None else ",".join(
                file_sha256(f) for f in weights_files(weights)),
            "gpd_weights_sha256": None if gpd_weights is None else file_sha256(gpd_weights),
            "config_hash": config_hash(yaml)}


def run_identity(experiment: Experiment, *, seed: int, objects_dir: str | None = None,
                 library=None) -> dict:
    """The identity of a run as run.json records it; two runs may share a folder only when
    theirs are equal (the trial count and the conditions asked for may differ).

    Keys, in the order a resume compares them: experiment, seed (the base seed),
    objects_dir, object_library_hash (`ObjectLibrary.content_hash`), conditions (every
    condition of the experiment: see `condition_identity`), code_tree
    (`provenance.code_tree`: the package, models and diagrams as committed, plus any
    uncommitted change to them - commits that touch only tests, docs or analysis scripts
    leave it, so a long run resumes across them).
    """
    if library is None:
        from drake_grasp.objects import load_library

        library = load_library(objects_dir)
    return {
        "experiment": experiment.name,
        "seed": int(seed),
        "objects_dir": objects_dir,
        "object_library_hash": library.content_hash(),
        "conditions": [condition_identity(experiment, c, objects_dir=objects_dir)
                       for c in experiment.conditions],
        "code_tree": code_tree(),
    }


def plugin_identity(experiment: Experiment, spec: str, *, objects_dir: str | None = None) -> dict:
    """What run.json records of a user policy's condition (under "plugin_conditions", by
    condition name): `condition_identity` plus its code (`plugins.policy_source`: module,
    file, sha256 of the file), so a resume with an edited policy file is refused."""
    from drake_grasp.policies.plugins import policy_source

    condition = plugin_condition(experiment, spec)
    identity = condition_identity(experiment, condition, objects_dir=objects_dir)
    if spec in EXTRA_POLICIES:  # a built-in: its code is the package's (`code_tree`)
        return identity
    return {**identity, "policy_source": policy_source(spec)}


def check_user_policy(experiment: Experiment, spec: str, *, objects_dir: str | None = None) -> None:
    """Builds a user policy once, with its condition's scenario, and checks its ports
    (`plugins.make_policy_system`), so a bad spec fails before any trial runs."""
    from drake_grasp.policies.plugins import make_policy_system

    if spec in EXTRA_POLICIES:  # a built-in policy: nothing of the user's to check
        return
    make_policy_system(spec, condition_scenario(experiment, plugin_condition(experiment, spec),
                                                objects_dir=objects_dir))


_MISSING = object()


def _differences(old, new, path: str = ""):
    """(key path, value in old, value in new) for every leaf where two JSON values differ;
    dict keys in `new`'s order, then those only in `old`."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in list(new) + [k for k in old if k not in new]:
            sub = f"{path}.{key}" if path else str(key)
            yield from _differences(old.get(key, _MISSING), new.get(key, _MISSING), sub)
    elif isinstance(old, list) and isinstance(new, list) and path.endswith("conditions"):
        for i in range(max(len(old), len(new))):
            yield from _differences(old[i] if i < len(old) else _MISSING,
                                    new[i] if i < len(new) else _MISSING, f"{path}[{i}]")
    elif old is _MISSING or new is _MISSING or old != new or type(old) is not type(new):
        yield path, old, new


def _show(value) -> str:
    if value is _MISSING:
        return "missing"
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= 120 else text[:119] + "…"


def folder_conflict(out: str | Path, identity: dict) -> str | None:
    """Why `out` cannot take trials of the run `identity` (see `run_identity`), or None
    when it can (it does not exist, is empty, or its run.json has the same identity).

    The reason names the first differing key, e.g. "conditions[1].scenario.controller.
    step_ratio: 0.2 in the folder, 0.3 now (and 2 more differences)".
    """
    from drake_grasp.evaluation.records import RUN_INFO_FILE, TRIALS_DIR, read_run_info, table_path

    out = Path(out)
    if not out.exists():
        return None
    if not out.is_dir():
        return f"{out}: exists and is not a folder"
    try:
        old = read_run_info(out)
    except FileNotFoundError:
        trials = out / TRIALS_DIR
        if table_path(out).is_file() or (
                trials.is_dir() and any(not p.name.startswith(".") for p in trials.iterdir())):
            return (f"{out}: holds trial records but no {RUN_INFO_FILE}, so what they were "
                    "run with is unknown")
        return None
    except ValueError as e:
        return str(e)
    base = {k: v for k, v in identity.items() if k != "plugin_conditions"}
    diffs = list(_differences({k: old.get(k, _MISSING) for k in base}, base))
    # User policies: only those both runs have are compared (a resume may add or leave out
    # user policies, as it may other conditions).
    old_plugins = old.get("plugin_conditions") or {}
    for name, ident in (identity.get("plugin_conditions") or {}).items():
        if name in old_plugins:
            diffs += list(_differences(old_plugins[name], ident, f"plugin_conditions.{name}"))
    if not diffs:
        return None
    key, was, now = diffs[0]
    more = f" (and {len(diffs) - 1} more difference{'s' if len(diffs) > 2 else ''})" \
        if len(diffs) > 1 else ""
    return f"{out / RUN_INFO_FILE}: {key}: {_show(was)} in the folder, {_show(now)} now{more}"


def choose_folder(out: str | Path, identity: dict, *, force_new: bool = False,
                  max_tries: int = 1000) -> tuple[Path, str | None]:
    """The folder a run goes to: `out` when it can take the run (`folder_conflict`).

    Otherwise, with `force_new`, the first of `OUT-2`, `OUT-3`, ... next to it that can:
    one that does not exist yet, or one that already holds this very run (so repeating a
    `--force-new` command after a kill resumes the folder it started, instead of starting
    yet another one).

    Returns:
        (folder, why `out` was not used or None).

    Raises:
        ValueError: `out` holds another run and not `force_new`; the message names the
            first differing key and says to use --force-new.
    """
    out = Path(out)
    conflict = folder_conflict(out, identity)
    if conflict is None:
        return out, None
    if not force_new:
        raise ValueError(f"{conflict}. Resuming into {out} would mix two different runs in "
                         "one folder; use --force-new to start a new run folder next to it "
                         f"({out.name}-2, ...), or choose another --out.")
    for k in range(2, max_tries + 2):
        candidate = out.with_name(f"{out.name}-{k}")
        if folder_conflict(candidate, identity) is None:
            return candidate, conflict
    raise ValueError(f"--force-new: {out.name}-2 ... {out.name}-{max_tries + 1} next to {out} "
                     "all hold other runs; choose another --out")
