"""Measure whether a walking walker's friction can be read from its last k=5 transitions.

An upper bound for what ZeUS's context can carry. A walking policy (the
shipped walker-walk-v0 weights) runs every training value of a family; each
sample is a context window exactly as psi sees it (k rows of (s, a, r, s')).
A regressor with psi's own architecture (the same MLP on every transition,
mean over the window, then a small head) is trained DIRECTLY on the true
friction, min-max scaled to [0, 1] over the train values, and tested on
held-out episodes (other start states). Test MSE near the variance of the
targets ("chance") means friction cannot be learned from such windows, so no
unsupervised context can be expected to carry it either.

It also reports how much one transition changes with friction: from states
along a walking trajectory, the same action is applied under each train
value, and the spread of s' is compared with the size of a step.

    PYTHONPATH=. python research/analysis/friction_identifiability.py   # about 10 CPU-minutes

Writes research/results/friction_identifiability.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import time

import numpy as np
import torch
from torch import nn

from figure4_spearman import windows_for
from sim_node.env import ParamEnv
from sim_node.families import get_family
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.core.window import ContextWindow

RESULTS = Path(__file__).resolve().parents[1] / 'results'
STATE_FIELDS = ('qpos', 'qvel', 'act', 'ctrl', 'qacc_warmstart')


def windows(model: InferenceModel, family: str, episodes: int, first_seed: int, steps: int):
    """Full context windows under the policy on every train value, and scaled targets."""
    spec = get_family(family)
    lo, hi = min(spec.train), max(spec.train)
    xs, ys = [], []
    for value in spec.train:
        rows = [r for r, _ in windows_for(family, value, episodes, steps, first_seed, model)]
        xs += rows
        ys += [(value - lo) / (hi - lo)] * len(rows)
    return np.asarray(xs, np.float32), np.asarray(ys, np.float32)


def fit(train, test, epochs: int, seed: int) -> tuple[float, float]:
    """Train the psi-shaped regressor; return (train MSE, test MSE), scaled units."""
    torch.manual_seed(seed)
    (x_tr, y_tr), (x_te, y_te) = train, test
    rows = x_tr.reshape(-1, x_tr.shape[-1])
    mean, std = rows.mean(0), rows.std(0) + 1e-6
    xt, yt = torch.from_numpy((x_tr - mean) / std), torch.from_numpy(y_tr)
    xe, ye = torch.from_numpy((x_te - mean) / std), torch.from_numpy(y_te)
    per_row = nn.Sequential(nn.Linear(xt.shape[-1], 256), nn.ReLU(), nn.Linear(256, 256),
                            nn.ReLU(), nn.Linear(256, 32))
    head = nn.Sequential(nn.Linear(32, 64), nn.ReLU(), nn.Linear(64, 1))

    def predict(x):
        return head(per_row(x).mean(1)).squeeze(-1)
    opt = torch.optim.Adam([*per_row.parameters(), *head.parameters()], lr=1e-3)
    for _ in range(epochs):
        perm = torch.randperm(len(xt))
        for i in range(0, len(xt), 256):
            idx = perm[i:i + 256]
            loss = ((predict(xt[idx]) - yt[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        return (float(((predict(xt) - yt) ** 2).mean()),
                float(((predict(xe) - ye) ** 2).mean()))


def one_step_spread(model: InferenceModel, family: str, steps: int = 300) -> tuple[float, float]:
    """Mean |s'(max train) - s'(min train)| and mean |s' - s| along a walk (L2 norms)."""
    spec = get_family(family)
    lo, hi = min(spec.train), max(spec.train)
    env = ParamEnv(family, (lo + hi) / 2, seed=0)
    obs = env.reset(seed=0)
    window = ContextWindow(model.k, env.obs_dim, env.action_dim)
    spread, step_size = [], []
    branches = {v: ParamEnv(family, v, seed=0) for v in (lo, hi)}
    for t in range(steps):
        action = model.act(obs, model.context(*window.arrays()))
        if t >= 100 and t % 10 == 0:
            state = {f: getattr(env.physics.data, f).copy() for f in STATE_FIELDS}
            nxt = {}
            for value, branch in branches.items():
                branch.reset(seed=0)
                for f, x in state.items():
                    getattr(branch.physics.data, f)[:] = x
                branch.physics.forward()
                nxt[value] = branch.step(action).observation
            spread.append(np.linalg.norm(nxt[hi] - nxt[lo]))
            step_size.append(np.linalg.norm(nxt[lo] - obs))
        result = env.step(action)
        window.push(obs, action, result.reward, result.observation)
        obs = result.observation
    return float(np.mean(spread)), float(np.mean(step_size))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', default='weights/walker-walk-v0-zeus',
                        help='a walking policy (its psi and actor drive the episodes)')
    parser.add_argument('--families', nargs='*',
                        default=['walker-walk-v0', 'walker-walk-slippery'])
    parser.add_argument('--train-seeds', type=int, nargs='*', default=[4, 16],
                        help='training-set sizes to try, in episodes per value')
    parser.add_argument('--steps', type=int, default=500, help='steps per episode')
    parser.add_argument('--epochs', type=int, default=30)
    parser.add_argument('--threads', type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    model = InferenceModel.load(args.weights)
    torch.set_num_threads(args.threads)  # InferenceModel.load sets one thread
    lines = ['# Can friction be read from k=5 transitions of a walking walker?', '',
             f'`PYTHONPATH=. python research/analysis/friction_identifiability.py` (policy: '
             f'`{args.weights}`, {args.steps}-step episodes, {args.epochs} epochs, '
             'psi-shaped regressor trained directly on the scaled friction; test = 2 held-out '
             'start states per value).', '',
             '| family | train values | episodes per value | windows | train MSE | test MSE '
             "| chance (variance) | one-step spread of s' / step size |",
             '|---|---|---|---|---|---|---|---|']
    for family in args.families:
        spec = get_family(family)
        started = time.monotonic()
        spread, step_size = one_step_spread(model, family)
        # Start states: seed * 100 + episode (figure4_spearman.windows_for), so
        # training episodes (seed 0) and test episodes (seed 1) never share one.
        test = windows(model, family, 2, 1, args.steps)
        for n in args.train_seeds:
            train = windows(model, family, n, 0, args.steps)
            train_mse, test_mse = fit(train, test, args.epochs, seed=0)
            row = (f'| {family} | {min(spec.train):g}-{max(spec.train):g} | {n} | '
                   f'{len(train[0])} | {train_mse:.4f} | {test_mse:.4f} | {test[1].var():.4f} '
                   f'| {spread:.2f} / {step_size:.2f} |')
            print(row, f'({time.monotonic() - started:.0f} s)', flush=True)
            lines.append(row)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / 'friction_identifiability.md').write_text('\n'.join(lines) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
