"""`train-grid` on a CUDA GPU: does a run resume across devices, and how fast does it train?

Run from the repository root on a machine with a CUDA GPU:

    python analysis/device_train_check.py --labels DIR --out result.json [--copies K]

`DIR` is a `drake-grasp dense-labels` folder (a few of its parts are enough). Three checks,
all through `dense_training.train` itself, the code `drake-grasp train-grid` runs:

1. **Resume across devices** (`tests/test_dense_training.py`'s GPU test, on real labels):
   the same 2-epoch run (plain grid net, Adam) whole on the CPU, and killed after 4
   batches on the CPU then resumed on the GPU; the final weights are compared with that
   test's tolerance (rtol 1e-4, atol 1e-5). Twice: on the test's size (12 images, batch
   4: 6 steps) and on all of `DIR`'s images at batch 50.
2. **Training throughput**: the default recipe (BatchNorm trunk, Adam, batch 50) and the
   paper's batch of 1000, on the CPU with all its cores and on the GPU, from scratch on
   `DIR`'s parts read `K` times over (`--copies`: an epoch long enough to time). Images
   per second over 2 epochs after a first warm-up epoch; each timed call loads the labels
   and saves its checkpoint and epoch weights, as a resumed `train-grid` run does.
3. **The step alone**: forward, backward and Adam on one batch already on the device,
   repeated: what the GPU could do if gathering the batch on the CPU cost nothing.

`train` runs in full float32 (`common.full_float32`: no TF32); `--no-tf32` does the same
for the step alone, which is outside `train`. Results on an H200:
`analysis/results/device-train-check/`.

Machines without Drake (a GPU machine that has only PyTorch): `train` reads the wrist
camera's height in the gripper frame from the gripper model through Drake
(`station.gripper_frame_offsets`). Without Drake this script stands in the value given by
`--camera-z` (-0.115 m, what `gripper_frame_offsets()[2].translation()[2]` gives with
this repository's gripper model; with Drake present the script checks the two agree).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import shutil
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CAMERA_Z_G_M = -0.115  # gripper_frame_offsets()[2].translation()[2]; checked when Drake is there


def stand_in_for_drake(camera_z: float) -> bool:
    """Without pydrake, put a `drake_grasp.world.station` holding only `gripper_frame_offsets`
    (the camera's pose in the gripper frame: its height `camera_z`) in sys.modules.
    Returns whether it did; with Drake, checks `camera_z` against the gripper model."""
    if importlib.util.find_spec("pydrake") is None:
        class _Pose:
            def translation(self):
                return np.array([0.0, 0.0, camera_z])

        mod = types.ModuleType("drake_grasp.world.station")
        mod.gripper_frame_offsets = lambda: (None, None, _Pose())
        sys.modules["drake_grasp.world.station"] = mod
        return True
    from drake_grasp.world.station import gripper_frame_offsets

    have = float(gripper_frame_offsets()[2].translation()[2])
    if abs(have - camera_z) > 1e-12:
        raise ValueError(f"--camera-z {camera_z}: the gripper model gives {have}")
    return False


def small_copy(labels: Path, out: Path, n: int) -> Path:
    """A labels folder holding the first `n` images of `labels`' first part."""
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(labels / "config.json", out / "config.json")
    first = sorted(labels.glob("shard-*.npz"))[0]
    with np.load(first) as z:
        np.savez(out / "shard-00000.npz", **{k: z[k][:n] for k in z.files})
    return out


def weight_diff(a_path: Path, b_path: Path) -> dict:
    from drake_grasp.cnn.weights_io import load_weights

    a, _ = load_weights(a_path)
    b, _ = load_weights(b_path)
    worst_abs, worst_rel, ok = 0.0, 0.0, True
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        d = (x - y).abs()
        worst_abs = max(worst_abs, float(d.max()))
        worst_rel = max(worst_rel, float((d / y.abs().clamp_min(1e-12)).max()))
        try:
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)
        except AssertionError:
            ok = False
    return {"within_rtol_1e-4_atol_1e-5": ok, "max_abs_diff": worst_abs,
            "max_rel_diff": worst_rel}


def resume_check(folders, work: Path, *, batch: int, lr: float, gpu: str,
                 threads: int) -> dict:
    from drake_grasp.learning.dense_training import train

    kw = dict(test_data=None, init=None, epochs=2, batch=batch, lr=lr, threads=threads,
              progress=False)
    train(folders, work / "cpu", device="cpu", **kw)
    train(folders, work / "mixed", device="cpu", _stop_after_batches=4, **kw)
    train(folders, work / "mixed", device=gpu, **kw)
    return weight_diff(work / "cpu" / "epoch2.safetensors",
                       work / "mixed" / "epoch2.safetensors")


def throughput(folders, work: Path, *, device: str, batch: int, threads: int,
               n_images: int) -> dict:
    from drake_grasp.learning.dense_training import train

    kw = dict(test_data=None, init=None, batch=batch, lr=2e-4, threads=threads,
              batch_norm=True, device=device, progress=False, checkpoint_minutes=1e9)
    t0 = time.perf_counter()
    train(folders, work, epochs=1, **kw)  # warm-up: first CUDA kernels, caches
    warm = time.perf_counter() - t0
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    metrics = train(folders, work, epochs=3, **kw)
    if device == "cuda":
        torch.cuda.synchronize()
    took = time.perf_counter() - t0
    return {"device": device, "batch": batch, "threads": threads, "images": n_images,
            "warmup_epoch_s": warm, "two_epochs_s": took,
            "images_per_s": 2 * n_images / took,
            "batches_per_s": 2 * -(-n_images // batch) / took,
            "train_l1_mm_epoch3": 1000 * metrics["epochs"][-1]["train_l1_m"]}


def step_alone(folder: Path, *, device: str, batch: int, steps: int) -> dict:
    """Forward, backward and Adam on one resident batch, `steps` times after 5 warm-ups."""
    from drake_grasp.learning.dense_labels import LabelStore
    from drake_grasp.learning.dense_training import BatchNormTrunk, batch_tensors
    from drake_grasp.cnn.net_config import NetworkConfig
    from drake_grasp.cnn.network import DistanceCNN
    from drake_grasp.world.station import gripper_frame_offsets

    cfg = NetworkConfig.from_dict(json.loads((folder / "config.json").read_text()))
    store = LabelStore([folder])
    idx = np.arange(min(batch, store.n_images))
    data = store.take(idx)
    model = BatchNormTrunk(DistanceCNN(cfg, generator=torch.Generator().manual_seed(0)))
    model.to(device)
    opt = torch.optim.Adam(model.parameters(), lr=2e-4)
    camera_z = float(gripper_frame_offsets()[2].translation()[2])
    images, target, mask = batch_tensors(model, data, cfg, camera_z, device)

    def step():
        loss = (model.image_features(images) - target).abs()[mask].mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(5):
        step()
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    if device == "cuda":
        torch.cuda.synchronize()
    took = time.perf_counter() - t0
    return {"device": device, "batch": len(idx), "steps": steps, "s": took,
            "images_per_s": steps * len(idx) / took}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--labels", required=True, help="a dense-labels folder")
    p.add_argument("--out", required=True, help="the JSON file to write")
    p.add_argument("--copies", type=int, default=10,
                   help="read the folder's parts this many times over per epoch (throughput)")
    p.add_argument("--camera-z", type=float, default=CAMERA_Z_G_M)
    p.add_argument("--cpu-threads", type=int, default=os.cpu_count())
    p.add_argument("--device", default="cuda", choices=("cuda", "cpu"),
                   help="the device checked against the CPU (cpu: a dry run of the script)")
    p.add_argument("--no-tf32", action="store_true",
                   help="torch.backends.{cudnn,cuda.matmul}.allow_tf32 = False for the "
                        "step alone (train() sets it itself): full float32 convolutions "
                        "(cuDNN's default on Ampere and later GPUs is TF32, a 10-bit "
                        "mantissa)")
    p.add_argument("--skip", default="", help="comma-separated: resume,throughput,step")
    args = p.parse_args(argv)
    labels = Path(args.labels)
    if not (labels / "config.json").is_file():
        print(f"{labels}: not a dense-labels folder (no config.json)", file=sys.stderr)
        return 2
    gpu = args.device
    if gpu == "cuda" and not torch.cuda.is_available():
        print("no CUDA GPU visible to torch: this check needs one (--device cpu: a dry "
              "run with the CPU in the GPU's place)", file=sys.stderr)
        return 2
    skip = set(filter(None, args.skip.split(",")))
    if args.no_tf32:
        torch.backends.cudnn.allow_tf32 = False
        torch.backends.cuda.matmul.allow_tf32 = False
    out = {"torch": torch.__version__,
           "gpu": torch.cuda.get_device_name(0) if gpu == "cuda" else None,
           "cpu_count": os.cpu_count(), "cpu": platform.processor() or platform.machine(),
           "drake_stand_in": stand_in_for_drake(args.camera_z), "camera_z_G_m": args.camera_z,
           "cudnn_allow_tf32": torch.backends.cudnn.allow_tf32,
           "matmul_allow_tf32": torch.backends.cuda.matmul.allow_tf32}
    from drake_grasp.learning.dense_labels import LabelStore

    n_images = LabelStore([labels]).n_images
    out["label_images"] = n_images
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if "resume" not in skip:
            small = small_copy(labels, tmp / "small", 12)
            out["resume_test_size"] = resume_check([small], tmp / "r1", batch=4, lr=1e-3,
                                                   gpu=gpu, threads=args.cpu_threads)
            print("resume, 12 images:", out["resume_test_size"], flush=True)
            out["resume_all_images"] = resume_check([labels], tmp / "r2", batch=50, lr=1e-3,
                                                    gpu=gpu, threads=args.cpu_threads)
            print(f"resume, {n_images} images:", out["resume_all_images"], flush=True)
        if "throughput" not in skip:
            rows = []
            for i, (device, batch) in enumerate(((gpu, 50), (gpu, 1000),
                                                 ("cpu", 50), ("cpu", 1000))):
                row = throughput([labels] * args.copies, tmp / f"t{i}-{device}-{batch}",
                                 device=device, batch=batch, threads=args.cpu_threads,
                                 n_images=n_images * args.copies)
                rows.append(row)
                print("train:", row, flush=True)
            out["throughput"] = rows
        if "step" not in skip:
            torch.set_num_threads(args.cpu_threads)
            out["step_alone"] = []
            for device, batch, steps in ((gpu, 50, 200), (gpu, 1000, 50),
                                         ("cpu", 50, 20), ("cpu", 1000, 3)):
                row = step_alone(labels, device=device, batch=batch, steps=steps)
                out["step_alone"].append(row)
                print("step:", row, flush=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
