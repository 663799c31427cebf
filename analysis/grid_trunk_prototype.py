"""Which trunk learns the grid head's dense labels fastest? One training loop for several
trunks on the same labels, the same batches and the same masked L1 as `train-grid`, with a
held-out check every --eval-every batches on --test-images images of a dense-labelled test
set: L1 over the in-view nodes, L1 where the label is under 3 cm, and the ranking of the
controller's candidate region among the grid's own nodes (x and y within 4 cm of the hand,
theta within 45 degrees: 9 x 9 x 9 nodes) - within-image Spearman against the labels,
the regret of the top-ranked node and how often it is within 1 cm of the best.

Trunks (--arch): `paper` (the package's grid `DistanceCNN`; --init starts from weights),
`pkgbn` (the same trained through `dense_training.BatchNormTrunk`; from --init its
BatchNorms start as the identity), `bn` (the paper's layers, each followed by a BatchNorm,
PyTorch's default initialisation) and `deep` (Conv1 32@5x5, pool, Conv 64@3x3, Conv
64@3x3, pool, IP1 500, a BatchNorm after each). Commands of analysis/results/cnn-batchnorm/:

    drake-grasp dense-labels --data data/paper_test --out data/paper_test_grid
    python analysis/grid_trunk_prototype.py --train data/near0_grid --test data/paper_test_grid \
        --arch bn --lr 1e-3 --epochs 2 --eval-every 400 --out bn_1e-3.json
"""
import argparse, glob, json, time, math
import numpy as np, torch, torch.nn as nn, torch.nn.functional as F
from drake_grasp.cnn.net_config import normalize_depth
from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.cnn.weights_io import load_weights
from drake_grasp.learning.dense_labels import view_masks, GRID_CONFIG
from drake_grasp.world.station import gripper_frame_offsets
from drake_grasp.learning.cnn_metrics import spearman

CFG = GRID_CONFIG
T, N, _ = CFG.grid_shape()
CAMZ = float(gripper_frame_offsets()[2].translation()[2])

def load(folders, limit=None):
    parts = []
    for f in folders.split(","):
        parts += sorted(glob.glob(f + "/shard-*.npz"))
    d = {"depth": [], "grid": [], "hand_z": []}
    n = 0
    for p in parts:
        z = np.load(p)
        for k in d: d[k].append(z[k])
        n += len(z["depth"])
        if limit and n >= limit: break
    return {k: np.concatenate(v)[:limit] for k, v in d.items()}

class BNNet(nn.Module):
    def __init__(self, kind, seed):
        super().__init__()
        torch.manual_seed(seed)
        self.kind = kind
        if kind == "bn":
            self.convs = nn.ModuleList([nn.Conv2d(1, 20, 5), nn.Conv2d(20, 50, 5)])
            self.bns = nn.ModuleList([nn.BatchNorm2d(20), nn.BatchNorm2d(50)])
            self.pools = [True, True]; flat = 50 * 13 * 13
        elif kind == "deep":
            self.convs = nn.ModuleList([nn.Conv2d(1, 32, 5), nn.Conv2d(32, 64, 3), nn.Conv2d(64, 64, 3)])
            self.bns = nn.ModuleList([nn.BatchNorm2d(32), nn.BatchNorm2d(64), nn.BatchNorm2d(64)])
            self.pools = [True, False, True]; flat = 64 * 13 * 13
        self.ip1 = nn.Linear(flat, 500); self.bn1 = nn.BatchNorm1d(500)
        self.ip2 = nn.Linear(500, T * N * N)
    def forward(self, x):
        for c, b, p in zip(self.convs, self.bns, self.pools):
            x = F.leaky_relu(b(c(x)), 0.01)
            if p: x = F.max_pool2d(x, 2)
        h = F.leaky_relu(self.bn1(self.ip1(x.flatten(1))), 0.01)
        return (0.05 * F.softplus(self.ip2(h))).view(-1, T, N, N)

class Paper(nn.Module):
    def __init__(self, seed, init=None):
        super().__init__()
        self.net = init if init is not None else DistanceCNN(CFG, generator=torch.Generator().manual_seed(seed))
    def forward(self, x):
        return self.net.image_features(x)

def masks(hz, grid):
    mx = torch.from_numpy(view_masks(hz, CFG, CAMZ))
    m = (mx[:, None, :, None] & mx[:, None, None, :]).expand(len(hz), T, N, N)
    return m & torch.isfinite(grid)

# candidate nodes: |x|, |y| <= 4 cm of the hand, |theta| <= 40 deg
half = (N - 1) // 2
xi = np.arange(half - 4, half + 5); yi = np.arange(half + 5 - 4, half + 5 + 5)
ti = np.array([t for t in range(T) if abs(-90 + 10 * t) <= 45])

def evaluate(model, test):
    model.eval(); out = {"l1": 0.0, "n": 0, "near": 0.0, "nn": 0}
    rhos, regrets = [], []
    with torch.no_grad():
        for s in range(0, len(test["depth"]), 200):
            x = normalize_depth(test["depth"][s:s+200].astype(np.float32), CFG)
            g = torch.from_numpy(test["grid"][s:s+200].astype(np.float32))
            p = model(x); m = masks(test["hand_z"][s:s+200], g)
            e = (p - g).abs()
            out["l1"] += float(e[m].sum()); out["n"] += int(m.sum())
            near = m & (g < 0.03); out["near"] += float(e[near].sum()); out["nn"] += int(near.sum())
            pc = p[:, ti][:, :, yi][:, :, :, xi].reshape(len(p), -1).numpy()
            gc = g[:, ti][:, :, yi][:, :, :, xi].reshape(len(p), -1).numpy()
            ok = np.isfinite(gc).all(1)
            rhos += list(spearman(pc[ok], gc[ok]))
            regrets += list(gc[ok][np.arange(ok.sum()), pc[ok].argmin(1)] - gc[ok].min(1))
    model.train()
    r = np.array(regrets)
    return {"test_l1_mm": 1000 * out["l1"] / out["n"], "test_near_l1_mm": 1000 * out["near"] / max(out["nn"], 1),
            "spearman": float(np.nanmean(rhos)), "regret_mm": 1000 * float(r.mean()), "top1_1cm": float(np.mean(r <= 0.01)),
            "eval_images": len(r)}

def main():
    a = argparse.ArgumentParser()
    a.add_argument("--train"); a.add_argument("--test"); a.add_argument("--arch")
    a.add_argument("--epochs", type=float, default=1); a.add_argument("--lr", type=float, default=2e-4)
    a.add_argument("--lr-decay", type=float, default=1.0)
    a.add_argument("--batch", type=int, default=50); a.add_argument("--eval-every", type=int, default=500)
    a.add_argument("--threads", type=int, default=1); a.add_argument("--out"); a.add_argument("--limit", type=int)
    a.add_argument("--init"); a.add_argument("--test-images", type=int, default=1000)
    a.add_argument("--save")
    args = a.parse_args(); torch.set_num_threads(args.threads)
    tr = load(args.train, args.limit)
    te_all = load(args.test)
    pick = np.sort(np.random.default_rng(5).choice(len(te_all["depth"]), args.test_images, replace=False))
    te = {k: v[pick] for k, v in te_all.items()}; del te_all
    if args.arch == "paper": model = Paper(0, load_weights(args.init)[0] if args.init else None)
    elif args.arch == "pkgbn":
        from drake_grasp.learning.dense_training import BatchNormTrunk
        net = load_weights(args.init)[0] if args.init else DistanceCNN(CFG, generator=torch.Generator().manual_seed(0))
        bt = BatchNormTrunk(net)
        if args.init:
            sample = np.sort(np.random.default_rng([0, 1]).choice(len(tr["depth"]), 1000, replace=False))
            bt.start_as_identity(normalize_depth(tr["depth"][sample].astype(np.float32), CFG))
        class W(nn.Module):
            def __init__(s, b): super().__init__(); s.b = b
            def forward(s, x): return s.b.image_features(x)
        model = W(bt)
    else: model = BNNet(args.arch, 0)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    n = len(tr["depth"]); log = []; step = 0; t0 = time.time(); tot = 0.0; cnt = 0
    total_steps = int(args.epochs * math.ceil(n / args.batch))
    per_epoch = math.ceil(n / args.batch)
    log.append({"step": 0, "s": 0, **evaluate(model, te)}); print(json.dumps(log[-1]), flush=True)
    epoch = 0
    while step < total_steps:
        order = np.random.default_rng([0, epoch]).permutation(n)
        for s in range(0, n, args.batch):
            if step >= total_steps: break
            idx = np.sort(order[s:s+args.batch])
            x = normalize_depth(tr["depth"][idx].astype(np.float32), CFG)
            g = torch.from_numpy(tr["grid"][idx].astype(np.float32))
            m = masks(tr["hand_z"][idx], g)
            loss = (model(x) - g).abs()[m].mean()
            opt.zero_grad(); loss.backward(); opt.step(); step += 1
            tot += float(loss); cnt += 1
            if step % args.eval_every == 0 or step == total_steps:
                log.append({"step": step, "epoch": step / per_epoch, "s": round(time.time() - t0),
                            "train_l1_mm": 1000 * tot / cnt, **evaluate(model, te)})
                tot = cnt = 0
                print(json.dumps(log[-1]), flush=True)
                json.dump({"args": vars(args), "log": log}, open(args.out, "w"), indent=1)
        epoch += 1
        for gp in opt.param_groups: gp["lr"] *= args.lr_decay
    if args.save: torch.save(model.state_dict(), args.save)

if __name__ == "__main__":
    main()
