"""Reproduce appendix Table 1: regress the true context from the last 5 (s, a) tuples.

For each dynamics family, a uniform random policy runs episodes in every
training task; each sample is the flattened last 5 (observation, action)
tuples at some step t >= 4 of an episode, the target is the task's parameter
min-max scaled to [0, 1] over the family's train values (so the MSE is in
units of the train range squared; multiply by the range squared for raw
units). A two-layer MLP (two hidden ReLU layers of 256) is trained with Adam
on the samples of some episodes and tested on held-out episodes (other
seeds). Writes research/results/table1_context_regression.{csv,md}.

    PYTHONPATH=. python research/analysis/table1_context_regression.py
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
import time

import numpy as np
import torch
from torch import nn

from sim_node.env import ParamEnv
from sim_node.families import get_family

PAPER = {'cheetah-run-v0': 5.12e-5, 'finger-spin-v0': 7.45e-5, 'walker-walk-v0': 7.22e-5,
         'walker-walk-v1': 6.41e-5}
RESULTS = Path(__file__).resolve().parents[1] / 'results'


def collect(family: str, episodes: int, steps: int, k: int, seed: int):
    """(X [N, k*(obs+act)], y_scaled [N], episode id [N]) from a uniform random policy."""
    spec = get_family(family)
    lo, hi = min(spec.train), max(spec.train)
    rng = np.random.default_rng(seed)
    xs, ys, eps = [], [], []
    ep_id = 0
    for v in spec.train:
        env = ParamEnv(family, v, seed=seed, episode_steps=steps)
        for e in range(episodes):
            obs = env.reset(seed=seed * 1000 + e)
            tuples = []
            for _ in range(steps):
                a = rng.uniform(-1, 1, env.action_dim)
                tuples.append(np.concatenate([obs, a]))
                res = env.step(a)
                if res.instability:
                    break
                obs = res.observation
            tuples = np.asarray(tuples, np.float32)
            for t in range(k - 1, len(tuples)):
                xs.append(tuples[t - k + 1:t + 1].reshape(-1))
                ys.append((v - lo) / (hi - lo))
                eps.append(ep_id)
            ep_id += 1
    return np.asarray(xs, np.float32), np.asarray(ys, np.float32), np.asarray(eps)


def fit(x_tr, y_tr, x_te, y_te, epochs: int, seed: int):
    """Train the MLP; return (train MSE, test MSE) in scaled units."""
    torch.manual_seed(seed)
    mean, std = x_tr.mean(0), x_tr.std(0) + 1e-6
    xt = torch.from_numpy((x_tr - mean) / std)
    yt = torch.from_numpy(y_tr)
    xe = torch.from_numpy((x_te - mean) / std)
    ye = torch.from_numpy(y_te)
    net = nn.Sequential(nn.Linear(xt.shape[1], 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(),
                        nn.Linear(256, 1))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    n = len(xt)
    for _ in range(epochs):
        perm = torch.randperm(n)
        for i in range(0, n, 256):
            idx = perm[i:i + 256]
            loss = ((net(xt[idx]).squeeze(-1) - yt[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    with torch.no_grad():
        tr = ((net(xt).squeeze(-1) - yt) ** 2).mean().item()
        te = ((net(xe).squeeze(-1) - ye) ** 2).mean().item()
    return tr, te


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--families', nargs='*', default=list(PAPER))
    p.add_argument('--episodes', type=int, default=24, help='per train value (2/3 for training)')
    p.add_argument('--steps', type=int, default=200, help='steps per episode')
    p.add_argument('--epochs', type=int, default=30)
    p.add_argument('--k', type=int, default=5)
    p.add_argument('--seed', type=int, default=0)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    RESULTS.mkdir(parents=True, exist_ok=True)
    rows = []
    for family in args.families:
        t0 = time.time()
        x, y, ep = collect(family, args.episodes, args.steps, args.k, args.seed)
        test = (ep % args.episodes) >= (2 * args.episodes) // 3  # last third of each task
        tr, te = fit(x[~test], y[~test], x[test], y[test], args.epochs, args.seed)
        spec = get_family(family)
        span = max(spec.train) - min(spec.train)
        rows.append({'family': family, 'param': spec.param_name,
                     'train_values': len(spec.train), 'samples_train': int((~test).sum()),
                     'samples_test': int(test.sum()), 'train_mse_scaled': f'{tr:.3g}',
                     'test_mse_scaled': f'{te:.3g}', 'test_mse_raw': f'{te * span ** 2:.3g}',
                     'predict_mean_mse_scaled': f'{float(np.var(y[test])):.3g}',
                     'paper_loss': f'{PAPER.get(family, float("nan")):.3g}',
                     'seconds': f'{time.time() - t0:.0f}'})
        print(rows[-1], flush=True)
    with open(RESULTS / 'table1_context_regression.csv', 'w', newline='') as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = ['# Appendix Table 1 reproduction: context regression from the last 5 (s, a)',
             '', f'Random policy, {args.episodes} episodes x {args.steps} steps per train value '
             f'(first two thirds of episodes train, last third test), k={args.k}, MLP '
             '2x256 ReLU, Adam 1e-3, '
             f'{args.epochs} epochs. Targets min-max scaled to [0, 1] over the train values '
             '(`_scaled`); `_raw` is in squared parameter units. `predict_mean` is the MSE '
             'of always predicting the mean (chance level).', '',
             '| family | param | train MSE (scaled) | test MSE (scaled) | test MSE (raw) '
             '| chance MSE (scaled) | paper loss |', '|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['family']} | {r['param']} | {r['train_mse_scaled']} | "
                     f"{r['test_mse_scaled']} | {r['test_mse_raw']} | "
                     f"{r['predict_mean_mse_scaled']} | {r['paper_loss']} |")
    (RESULTS / 'table1_context_regression.md').write_text('\n'.join(lines) + '\n')


if __name__ == '__main__':
    main()
