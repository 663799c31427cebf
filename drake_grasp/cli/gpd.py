"""`drake-grasp` commands: the GPD baseline's classifier: data, training, held-out metrics (gpd-generate, gpd-train, gpd-eval, gpd-combine)."""

from __future__ import annotations

import json
import sys

from drake_grasp.cli.args import add_scenario_flags, load_scenario_from_args


def _cmd_gpd_generate(args) -> int:
    from drake_grasp.learning.gpd_training import GpdDataConfig, generate

    kinds = tuple(k for k in args.scene_kinds.split(",") if k)
    allowed = GpdDataConfig().scene_kinds
    if not kinds or any(k not in allowed for k in kinds):
        print(f"--scene-kinds {args.scene_kinds!r}: expected a comma-separated list of "
              f"{', '.join(allowed)}", file=sys.stderr)
        return 2
    if not args.settle_max_time > 0:
        print(f"--settle-max-time {args.settle_max_time}: expected seconds > 0", file=sys.stderr)
        return 2
    focus = tuple(c for c in args.focus_categories.split(",") if c)
    scenario = load_scenario_from_args(args, seed=args.seed)
    summary = generate(out=args.out, num_scenes=args.scenes, split=args.split, seed=args.seed,
                       scenario=scenario,
                       config=GpdDataConfig(candidates_per_scene=args.candidates_per_scene,
                                            scene_kinds=kinds,
                                            settle_max_time_s=args.settle_max_time,
                                            focus_categories=focus),
                       workers=args.workers, objects_dir=args.objects)
    print(json.dumps({k: summary[k] for k in ("num_scenes", "candidates", "positives")}))
    return 0


def _cmd_gpd_train(args) -> int:
    from drake_grasp.learning.gpd_training import GpdTrainConfig, train

    metrics = train(data=args.data, test_data=args.test_data, out=args.out,
                    config=GpdTrainConfig(epochs=args.epochs, seed=args.seed,
                                          threads=args.threads))
    print(json.dumps(metrics["held_out"]))
    return 0


def _cmd_gpd_eval(args) -> int:
    from drake_grasp.learning.gpd_training import evaluate_classifier

    result = evaluate_classifier(weights=args.weights or "", data=args.data, threads=args.threads)
    if args.out:
        from drake_grasp.core.files import atomic_write_text

        atomic_write_text(args.out, json.dumps(result, indent=1))
    rows = [("all", result["held_out"])] + list(result["by_category"].items())
    print(f"{'category':18s} {'candidates':>10s} {'positives':>9s}  precision / recall "
          "at 0.5 | 0.9")
    for name, m in rows:
        a, b = m["0.5"], m["0.9"]
        print(f"{name:18s} {a['num']:10d} {a['positives']:9d}  {a['precision']:.3f} / "
              f"{a['recall']:.3f} | {b['precision']:.3f} / {b['recall']:.3f}")
    return 0


def _cmd_gpd_combine(args) -> int:
    from drake_grasp.policies.gpd import combine_classifiers
    from drake_grasp.core.provenance import file_sha256

    model = combine_classifiers(args.weights, args.out)
    print(f"{args.out}: mean of {len(model.members)} classifiers, sha256 {file_sha256(args.out)}")
    return 0


def _parser_gpd_generate(sub) -> None:
    p = sub.add_parser("gpd-generate", help="training data of the GPD baseline's grasp "
                                             "classifier (labelled candidates and grasp "
                                             "images in .npz shards); re-running resumes")
    add_scenario_flags(p, default="random")
    p.add_argument("--scenes", type=int, required=True,
                   help="number of scenes (isolation, random and clutter in turn)")
    p.add_argument("--split", required=True, choices=["train", "test"],
                   help="object instances to use (test: held-out instances)")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    p.add_argument("--seed", type=int, default=0, help="data seed (default 0)")
    p.add_argument("--out", required=True, help="data folder")
    p.add_argument("--candidates-per-scene", type=int, default=600,
                   help="labelled candidates kept per scene: positives up to a quarter, "
                        "negatives fill up (default 600)")
    p.add_argument("--focus-categories", default="", metavar="A,B",
                   help="object categories every scene holds one instance of (e.g. "
                        "hammer,flashlight: more data where the classifier is weakest, see "
                        "gpd-eval); default: objects drawn as the experiments draw them")
    p.add_argument("--scene-kinds", default="isolation,random,clutter",
                   help="scene kinds drawn in turn (default isolation,random,clutter); "
                        "'clutter' piles have the scenario's scene.clutter_objects objects")
    p.add_argument("--settle-max-time", type=float, default=2.0, metavar="S",
                   help="simulated seconds a scene may take to come to rest before another "
                        "seed is drawn (default 2.0; 10-object pours can need the "
                        "experiments' 4)")
    p.set_defaults(func=_cmd_gpd_generate)


def _parser_gpd_train(sub) -> None:
    p = sub.add_parser("gpd-train", help="train the GPD baseline's grasp classifier (Adam, "
                                          "class-weighted cross-entropy); re-running resumes")
    p.add_argument("--data", required=True, help="gpd-generate folder of the train split, or "
                                                  "several, comma-separated (concatenated)")
    p.add_argument("--test-data", required=True,
                   help="gpd-generate folder of the test split (held-out object instances)")
    p.add_argument("--out", required=True,
                   help="output folder (checkpoint.pt, metrics.json, weights.safetensors)")
    p.add_argument("--epochs", type=int, default=12, help="epochs (default 12)")
    p.add_argument("--seed", type=int, default=0, help="initial weights and shuffling seed")
    p.add_argument("--threads", type=int, default=2, help="CPU threads (default 2)")
    p.set_defaults(func=_cmd_gpd_train)


def _parser_gpd_eval(sub) -> None:
    p = sub.add_parser("gpd-eval", help="held-out precision and recall of a GPD classifier, "
                                         "over all candidates and per object category")
    p.add_argument("--data", required=True, help="gpd-generate folder(s) to score, "
                                                  "comma-separated (e.g. a test split)")
    p.add_argument("--weights", default="", help="classifier weights (a gpd-train "
                                                  "weights.safetensors); default: the shipped one")
    p.add_argument("--out", default="", help="also write the metrics as JSON to this file")
    p.add_argument("--threads", type=int, default=2, help="CPU threads (default 2)")
    p.set_defaults(func=_cmd_gpd_eval)


def _parser_gpd_combine(sub) -> None:
    p = sub.add_parser("gpd-combine", help="one GPD weights file whose probabilities are the "
                                            "mean of several classifiers' (an ensemble)")
    p.add_argument("weights", nargs="+", help="classifier weights files (gpd-train "
                                               "weights.safetensors), at least 2")
    p.add_argument("--out", required=True, help="the ensemble's safetensors file")
    p.set_defaults(func=_cmd_gpd_combine)


def add_parsers(sub) -> None:
    """Add this group's subcommands to the `drake-grasp` parser."""
    _parser_gpd_generate(sub)
    _parser_gpd_train(sub)
    _parser_gpd_eval(sub)
    _parser_gpd_combine(sub)
