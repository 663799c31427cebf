"""`drake-grasp` commands: the simulated training set and the distance CNN's training (generate, inspect-data, train, dense-labels, train-grid, checkpoint-weights)."""

from __future__ import annotations

import json
import sys

from drake_grasp.cli.args import (add_scenario_flags, load_scenario_from_args, positive_float,
                                  non_negative_float, positive_int, trunk_widths,
                                  add_torque_ratio_flag, add_initial_pose_flag)


def _cmd_generate(args) -> int:
    from drake_grasp.learning.dataset import DatasetConfig
    from drake_grasp.learning.dataset_generate import generate_dataset

    scenario = load_scenario_from_args(args, seed=args.seed)
    config = DatasetConfig(images_per_scene=args.images_per_scene,
                           offsets_per_image=args.offsets_per_image,
                           scenes_per_shard=args.scenes_per_shard,
                           max_torque_ratio=args.max_torque_ratio,
                           grasp_samples=args.grasp_samples,
                           near_grasp_fraction=args.near_grasp_fraction,
                           scene_kind=args.scene_kind, initial_pose=args.initial_pose,
                           settle_max_time_s=args.settle_max_time)
    manifest = generate_dataset(out=args.out, num_scenes=args.scenes, split=args.split,
                                seed=args.seed, scenario=scenario, config=config,
                                workers=args.workers, scheduler=args.scheduler,
                                objects_dir=args.objects)
    print(json.dumps({k: manifest[k] for k in (
        "num_scenes", "num_images", "num_labels", "num_shards", "num_scene_attempts",
        "num_scenes_unsettled_resampled", "num_scenes_no_grasp_resampled")}))
    return 0


def _cmd_inspect_data(args) -> int:
    from drake_grasp.learning.datavis import inspect_dataset

    print(inspect_dataset(args.data, out=args.out, num_images=args.images, seed=args.seed))
    return 0


def _cmd_train(args) -> int:
    from drake_grasp.learning.training import TrainConfig, train

    config = TrainConfig.from_recipe(
        args.recipe, epochs=args.epochs, batch_instances=args.batch, optimizer=args.optimizer,
        learning_rate=args.lr, momentum=args.momentum, lr_decay_per_epoch=args.lr_decay,
        seed=args.seed, device=args.device, threads=args.threads,
        max_memory_gb=args.max_memory_gb, checkpoint_minutes=args.checkpoint_minutes,
        ranking_images=args.ranking_images, init_weights=args.init_weights,
        loss=args.loss, loss_offset_m=args.loss_offset)
    if args.loss_offset is not None and args.loss != "log-l1":
        print("--loss-offset: needs --loss log-l1", file=sys.stderr)
        return 2
    network = None  # the default net (or the --init-weights file's)
    if args.context_side and args.action_fusion != "window":
        print("--context-side: needs --action-fusion window", file=sys.stderr)
        return 2
    if args.action_fusion == "window":
        from drake_grasp.cnn.net_config import NetworkConfig
        try:
            network = NetworkConfig(theta_unit="deg", action_fusion="window",
                                    context_side_m=args.context_side)
        except ValueError as e:
            print(f"--context-side {args.context_side}: {e}", file=sys.stderr)
            return 2
    metrics = train(data=args.data, test_data=args.test_data, out=args.out, config=config,
                    network=network)
    print(json.dumps({"test_l1_m": metrics.get("test_l1_m"), "epochs": len(metrics["epochs"]),
                      "device": metrics["device"], "out": str(args.out)}))
    return 0


def _cmd_dense_labels(args) -> int:
    from drake_grasp.learning.dense_labels import build_labels

    images = build_labels(args.data, args.out, workers=args.workers)
    print(json.dumps({"out": str(args.out), "images_labelled_now": images}))
    return 0


def _cmd_train_grid(args) -> int:
    from drake_grasp.learning.dense_training import train as train_grid

    metrics = train_grid([f for f in args.labels.split(",") if f], args.out,
                         test_data=args.test_data, init=args.init_weights, epochs=args.epochs,
                         batch=args.batch, lr=args.lr, lr_decay=args.lr_decay, seed=args.seed,
                         threads=args.threads, checkpoint_minutes=args.checkpoint_minutes,
                         trunk=args.trunk, batch_norm=args.batch_norm, device=args.device,
                         stream_shards=args.stream_shards, augment=args.augment,
                         rank_weight=args.rank_weight, rank_scale_m=args.rank_scale_m)
    last = metrics["epochs"][-1] if metrics["epochs"] else {}
    print(json.dumps({"out": str(args.out), "epochs": len(metrics["epochs"]),
                      **{k: last[k] for k in ("train_l1_m", "test_l1_m") if k in last}}))
    return 0


def _cmd_checkpoint_weights(args) -> int:
    from drake_grasp.learning.training import export_checkpoint_weights

    meta = export_checkpoint_weights(args.run, args.out)
    print(json.dumps({"out": str(args.out), **{k: meta[k] for k in (
        "checkpoint_epoch", "checkpoint_next_batch", "iterations")}}))
    return 0


def _parser_generate(sub) -> None:
    p = sub.add_parser("generate", help="generate the simulated training set (HDF5 shards + "
                                         "manifest.json); re-running resumes")
    add_scenario_flags(p, default="random")
    p.add_argument("--scenes", type=int, required=True,
                   help="number of labelled scenes, exactly: a scene that does not settle "
                        "or has no true grasp is replaced by the next seed reserved for it "
                        "(counted in manifest.json); re-running with a larger N extends the "
                        "dataset. One generator per folder: a second one is refused")
    p.add_argument("--split", required=True, choices=["train", "test"],
                   help="object instances to use (the split is by instance)")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the tasks on this Dask distributed scheduler instead")
    p.add_argument("--seed", type=int, default=0, help="dataset seed (default 0)")
    p.add_argument("--out", required=True, help="dataset folder")
    p.add_argument("--images-per-scene", type=int, default=40,
                   help="camera poses per scene (paper: 40)")
    add_torque_ratio_flag(p)
    add_initial_pose_flag(p)
    from drake_grasp.learning.dataset import SCENE_KINDS, DatasetConfig

    p.add_argument("--grasp-samples", type=positive_int, default=DatasetConfig().grasp_samples,
                   metavar="N",
                   help="surface points of the ground-truth grasp search per scene (default "
                        f"{DatasetConfig().grasp_samples}, ~0.12 s; more gives less noisy labels "
                        "at proportional cost: README *How exact the labels are*)")
    p.add_argument("--near-grasp-fraction", type=float, default=0.0, metavar="F",
                   help="draw this fraction of each scene's hand poses near a true grasp "
                        "(within the controller's candidate range: 4 cm, 45 degrees) instead "
                        "of at random (default 0, the paper's random poses; README *Views "
                        "near a grasp*)")
    p.add_argument("--scene-kind", choices=list(SCENE_KINDS), default="random",
                   help="random: the paper's scenes, 1-5 objects spread out (default); "
                        "clutter: the scenario's scene.clutter_objects poured into a pile "
                        "as in the clutter experiments (set them with --scenario-text, e.g. "
                        "'{scene: {clutter_objects: 10, region_half_extent_m: 0.06}}'; "
                        "README *Training on piles*)")
    p.add_argument("--settle-max-time", type=float, default=DatasetConfig().settle_max_time_s,
                   metavar="S",
                   help="simulated seconds a scene may take to come to rest before the next "
                        f"seed reserved for it is drawn (default {DatasetConfig().settle_max_time_s};"
                        " 10-object pours need about 6)")
    p.add_argument("--offsets-per-image", type=int, default=10,
                   help="labelled offsets per image (paper: 10)")
    p.add_argument("--scenes-per-shard", type=int, default=4,
                   help="scenes per shard file, i.e. per worker task (default 4); the "
                        "last shard holds the rest")
    p.set_defaults(func=_cmd_generate)


def _parser_inspect_data(sub) -> None:
    p = sub.add_parser("inspect-data", help="picture of a dataset: depth images with true "
                                            "grasps and labelled offsets, label histogram")
    p.add_argument("data", help="dataset folder")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--images", type=int, default=12, help="images to draw (default 12)")
    p.add_argument("--seed", type=int, default=0, help="which images (default 0)")
    p.set_defaults(func=_cmd_inspect_data)


def _parser_train(sub) -> None:
    p = sub.add_parser("train", help="train the distance CNN (L1 loss); re-running resumes")
    p.add_argument("--data", required=True,
                   help="train-split dataset folder, or a folder holding train/ and test/")
    p.add_argument("--test-data", default=None,
                   help="test-split dataset folder (held-out object instances)")
    p.add_argument("--out", required=True, help="output folder (checkpoints, metrics, weights)")
    p.add_argument("--epochs", type=int, default=10, help="epochs (default 10)")
    p.add_argument("--recipe", choices=["fast", "paper"], default="fast",
                   help="fast (default): Adam, lr 0.0001 decaying x0.8 per epoch; paper: SGD "
                        "lr 0.001, momentum 0.9, constant. The flags below override it")
    p.add_argument("--optimizer", choices=["sgd", "adam"], default=None,
                   help="optimizer (default: the recipe's)")
    p.add_argument("--batch", type=int, default=None,
                   help="instances (image, offset, label) per batch (both recipes and the "
                        "paper: 1000)")
    p.add_argument("--lr", type=float, default=None,
                   help="learning rate of the first epoch (fast: 0.0001, paper: 0.001)")
    p.add_argument("--lr-decay", type=float, default=None,
                   help="learning-rate factor per epoch, in (0, 1] (fast: 0.8, paper: 1)")
    p.add_argument("--momentum", type=float, default=None,
                   help="SGD momentum (paper: 0.9); Adam ignores it")
    p.add_argument("--checkpoint-minutes", type=float, default=None,
                   help="checkpoint at least this often within an epoch (default 5); a "
                        "killed run resumes from it with the batches still to come. May "
                        "differ when resuming")
    p.add_argument("--ranking-images", type=int, default=None,
                   help="held-out images for the within-image rank correlation after each "
                        "epoch (default 200; 0: none)")
    p.add_argument("--seed", type=int, default=0, help="initial weights and shuffling seed")
    p.add_argument("--device", default="auto",
                   help="auto (GPU when present), cpu or cuda; may differ when resuming "
                        "(a run started on a CPU continues on a GPU and back)")
    p.add_argument("--threads", type=int, default=0,
                   help="CPU threads (0: torch default); may differ when resuming")
    p.add_argument("--max-memory-gb", type=float, default=8.0,
                   help="most memory the data loader may hold, in GB (default 8): cached "
                        "HDF5 chunks of both sets plus the batch being assembled; larger "
                        "datasets stream from the shards (slower epochs, the same batches). "
                        "Too small for one batch is an error. May differ when resuming")
    p.add_argument("--init-weights", default=None, metavar="FILE",
                   help="start from these weights (e.g. the shipped "
                        "models/cnn/weights.safetensors) instead of a fresh initialization, "
                        "with a fresh optimizer; their tensors' sha256 is part of the run's "
                        "identity")
    p.add_argument("--loss", choices=("l1", "log-l1"), default=None,
                   help="training loss: l1 (default, the paper's) or log-l1, the L1 of "
                        "log(distance + c), whose weight falls as 1/(distance + c): errors "
                        "near a grasp cost more than far ones (README *Near-weighted loss*)")
    p.add_argument("--loss-offset", type=float, default=None, metavar="M",
                   help="c of --loss log-l1, in metres (default 0.01)")
    p.add_argument("--action-fusion", choices=("tiled", "window"), default="tiled",
                   help="how the candidate action enters the net: tiled (default, the "
                        "paper's: IP(a) added to every Pool1 cell) or window (the net reads "
                        "its Conv2 features in a 12 cm window placed and turned where the "
                        "candidate grasp would be; README *Window fusion*)")
    p.add_argument("--context-side", type=float, default=0.0, metavar="M",
                   help="with --action-fusion window: side in metres of a second, coarser "
                        "window around the candidate (as many samples as the 12 cm one), "
                        "so the net sees what lies beyond it; 0 (default): none")
    p.set_defaults(func=_cmd_train)


def _parser_dense_labels(sub) -> None:
    p = sub.add_parser("dense-labels", help="label every node of the grid head's action grid "
                       "on every image of a dataset (for train-grid); re-running skips the "
                       "shards already done")
    p.add_argument("--data", required=True, help="dataset folder (generate --out)")
    p.add_argument("--out", required=True, help="folder for the labels (one .npz per shard)")
    p.add_argument("--workers", type=positive_int, default=2, help="worker processes (default 2)")
    p.set_defaults(func=_cmd_dense_labels)


def _parser_train_grid(sub) -> None:
    p = sub.add_parser("train-grid", help="train the grid-head distance CNN on dense labels "
                       "(L1 over every in-view grid node); re-running resumes")
    p.add_argument("--labels", required=True,
                   help="dense-labels folders, comma-separated (the same grid)")
    p.add_argument("--out", required=True, help="run folder: epochN.safetensors, metrics.json, "
                   "checkpoint.pt")
    p.add_argument("--test-data", default=None, help="dataset folder for the test L1 and "
                   "ranking metrics after every epoch (e.g. a generate --split test folder)")
    p.add_argument("--init-weights", default=None, metavar="FILE",
                   help="start from these weights: a paper (tiled) net's Conv1, Conv2 and "
                        "IP1 with its distance for staying put on every node, or a grid net")
    p.add_argument("--epochs", type=positive_int, default=3)
    p.add_argument("--batch", type=positive_int, default=50, help="images per batch")
    p.add_argument("--lr", type=positive_float, default=2e-4, help="Adam's learning rate")
    p.add_argument("--lr-decay", type=positive_float, default=0.7,
                   help="learning-rate factor after every epoch")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=positive_int, default=2)
    p.add_argument("--checkpoint-minutes", type=positive_float, default=5.0)
    p.add_argument("--trunk", type=trunk_widths, default=None, metavar="C1,C2,H",
                   help="Conv1 filters, Conv2 filters and IP1 width (default: the paper's "
                        "20,50,500), e.g. 40,100,1000 for a wider net; --init-weights must "
                        "then have the same trunk")
    p.add_argument("--batch-norm", action="store_true",
                   help="train with a BatchNorm after Conv1, Conv2 and IP1 (folded into "
                        "them in the weights written: a plain grid net); from "
                        "--init-weights they start as the identity")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                   help="where the batches run: auto (a GPU when torch sees one), cpu or "
                        "cuda; may differ when resuming")
    p.add_argument("--stream-shards", type=positive_int, default=None, metavar="G",
                   help="keep the labels on disk and hold only groups of G label parts at "
                        "a time (an epoch permutes the parts, then the images within each "
                        "group): for label sets larger than memory (300,000 images take "
                        "14 GB in memory); default: every label in memory")
    p.add_argument("--augment", default="none", choices=("none", "mirror", "d4"),
                   help="train on each image (and its labels) under a random symmetry of "
                        "the wrist camera: mirror (flipped left-right or not) or d4 (also "
                        "turned 0, 90, 180 or 270 degrees about the optical axis); "
                        "default none")
    p.add_argument("--rank-weight", type=non_negative_float, default=0.0, metavar="W",
                   help="add W times a pairwise ranking loss to the L1: 1,024 pairs of "
                        "nearby grid nodes per image (within 4 cm and 40 degrees), the "
                        "logistic loss of ordering each pair as its labels do "
                        "(dense_training.pairwise_rank_loss); default 0 (L1 only)")
    p.add_argument("--rank-scale-m", type=positive_float, default=0.01, metavar="S",
                   help="with --rank-weight: the distance difference [m] the logistic "
                        "loss counts as one unit (default 0.01)")
    p.set_defaults(func=_cmd_train_grid)


def _parser_checkpoint_weights(sub) -> None:
    p = sub.add_parser("checkpoint-weights", help="write the weights of a training run's "
                       "latest checkpoint (an unfinished run) as a weights file for the "
                       "controller; the run may go on")
    p.add_argument("run", help="the run's output folder (train --out or train-grid --out)")
    p.add_argument("--out", required=True, help="weights file to write (*.safetensors)")
    p.set_defaults(func=_cmd_checkpoint_weights)


def add_parsers(sub) -> None:
    """Add this group's subcommands to the `drake-grasp` parser."""
    _parser_generate(sub)
    _parser_inspect_data(sub)
    _parser_train(sub)
    _parser_dense_labels(sub)
    _parser_train_grid(sub)
    _parser_checkpoint_weights(sub)
