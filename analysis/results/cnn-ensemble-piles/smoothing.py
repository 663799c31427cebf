"""Spatial smoothing of the default net's scores on the held-out piles: each candidate scored as
the mean over a stencil of offsets around it (x, y +-r; with a theta step, the 3x3x3 grid).
A check of whether the piles' ranking errors are noise between nearby offsets.

    PYTHONPATH=. python analysis/results/cnn-ensemble-piles/smoothing.py \\
        models/cnn-grid-bn12500-ep3/weights.safetensors data/clutter_test > analysis/results/cnn-ensemble-piles/smoothing.txt
"""
import sys

import numpy as np
import torch
from torch import nn
from drake_grasp.cnn.weights_io import load_weights
from drake_grasp.learning.cnn_metrics import ranking_metrics
torch.set_num_threads(1)
class Smoothed(nn.Module):
    def __init__(s, base, r_m, r_deg, grid):
        super().__init__(); s.base=base; s.config=base.config
        pts=[]
        ks = [-1,0,1] if grid else [0]
        for i in ([-1,0,1]): 
            for j in [-1,0,1]:
                for k in ks:
                    if grid or (abs(i)+abs(j)<=1):
                        pts.append((i*r_m, j*r_m, k*r_deg))
        s.st=np.array(pts,np.float32)
    @property
    def dtype(s): return s.base.dtype
    def preprocess(s,d): return s.base.preprocess(d)
    def image_features(s,x): return s.base.image_features(x)
    def score_actions(s,f,a):
        a=np.asarray(a,np.float32); K=len(a)
        aa=(a[:,None,:]+s.st[None]).reshape(-1,3)
        return s.base.score_actions(f,aa).reshape(K,-1).mean(1)
m,_=load_weights(sys.argv[1]); m.eval()
print("stencil_mm stencil_deg full_grid spearman_mean regret_median_mm regret_mean_mm top1_within_1cm")
for r_mm, r_deg, grid in [(0,0,False),(5,0,False),(10,0,False),(20,0,False),(10,10,True)]:
    mm = m if r_mm==0 else Smoothed(m, r_mm/1000, r_deg, grid)
    r=ranking_metrics(mm, sys.argv[2], images=200, seed=0)
    print(r_mm, r_deg, grid, round(r['spearman_mean'],3), round(r['regret_median_m']*1000,1), round(r['regret_mean_m']*1000,1), r['top1_within_1cm'], flush=True)
