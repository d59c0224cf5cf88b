"""Reproduce Figure 4: rank correlation of learned context vs true parameter distances.

Trains (or reuses) two cheetah-run-v0 runs of the same length and seed, with
the context loss (alpha_psi = 1, Table 11) and without (alpha_psi = 0, the
ZeUS-no-context-loss ablation), then for each run:

1. collects context windows in every training task (all 11 train values of
   Table 3; the paper's Figure 4 shows 8 tasks) from the SAME uniform-random
   trajectories for both runs (so only the encoders differ) and, separately,
   from each run's own deterministic policy;
2. encodes each full window (k = 5) with the run's psi and averages the latents
   per task;
3. computes the Spearman rank correlation between the pairwise L2 distances of
   the task latents and the pairwise |c_i - c_j| (55 pairs), and, as a
   sample-level check, over random pairs of single windows from different
   tasks.

Writes repro/results/figure4_spearman.{csv,md,png}.

    PYTHONPATH=. python repro/figure4_spearman.py --train-minutes 20
    PYTHONPATH=. python repro/figure4_spearman.py --runs runs/fig4-cheetah-alpha1.0 \
        runs/fig4-cheetah-alpha0.0          # analyse existing runs
"""

from __future__ import annotations

import argparse
import csv
from itertools import combinations
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr
import torch

from sim_node.env import ParamEnv
from sim_node.families import get_family
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.core.window import ContextWindow

FAMILY = 'cheetah-run-v0'
RESULTS = Path(__file__).resolve().parent / 'results'


def windows_for(family, value, episodes, steps, seed, model=None):
    """Full windows (rows, mask) along trajectories; random policy if model is None."""
    env = ParamEnv(family, value, seed=seed, episode_steps=steps)
    rng = np.random.default_rng(seed)
    out = []
    for e in range(episodes):
        obs = env.reset(seed=seed * 100 + e)
        w = ContextWindow(5, env.obs_dim, env.action_dim)
        for _ in range(steps):
            if model is None:
                a = rng.uniform(-1, 1, env.action_dim)
            else:
                a = model.act(obs, model.context(*w.arrays()))
            res = env.step(a)
            if res.instability:
                break
            w.push(obs, a, res.reward, res.observation)
            obs = res.observation
            if w.fill == w.k:
                out.append(w.arrays())
    return out


def latents(model, wins):
    rows = torch.from_numpy(np.stack([r for r, _ in wins]))
    mask = torch.from_numpy(np.stack([m for _, m in wins]))
    with torch.no_grad():
        return model.psi(rows, mask).numpy()


def spearman_tasks(values, task_latents):
    means = [z.mean(0) for z in task_latents]
    pairs = list(combinations(range(len(values)), 2))
    learned = [np.linalg.norm(means[i] - means[j]) for i, j in pairs]
    true = [abs(values[i] - values[j]) for i, j in pairs]
    return float(spearmanr(learned, true).statistic), learned, true


def spearman_samples(values, task_latents, n=5000, seed=0):
    rng = np.random.default_rng(seed)
    learned, true = [], []
    for _ in range(n):
        i, j = rng.choice(len(values), 2, replace=False)
        a = task_latents[i][rng.integers(len(task_latents[i]))]
        b = task_latents[j][rng.integers(len(task_latents[j]))]
        learned.append(np.linalg.norm(a - b))
        true.append(abs(values[i] - values[j]))
    return float(spearmanr(learned, true).statistic)


def train_runs(minutes: float, seed: int) -> list[Path]:
    from zeus_ros import train
    runs = []
    for alpha in (1.0, 0.0):
        out = Path('runs') / f'fig4-cheetah-alpha{alpha}'
        train.main(['--family', FAMILY, '--seed', str(seed), '--out', str(out),
                    '--alpha-psi', str(alpha), '--steps', '1000000',
                    '--time-limit', str(minutes), '--eval-every', '0',
                    '--no-save-replay', '--quiet', '--set', 'num_threads=1'])
        runs.append(out)
    return runs


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--runs', nargs='+', type=Path, default=None,
                   help='existing run dirs in pairs (with context loss, without), one pair '
                        'per seed')
    p.add_argument('--train-minutes', type=float, default=20.0)
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--episodes', type=int, default=2)
    p.add_argument('--steps', type=int, default=300)
    args = p.parse_args(argv)
    runs = args.runs or train_runs(args.train_minutes, args.seed)
    if len(runs) % 2:
        raise SystemExit('--runs takes pairs: with context loss, then without')
    values = list(get_family(FAMILY).train)
    random_wins = [windows_for(FAMILY, v, args.episodes, args.steps, 7) for v in values]
    rows, plots = [], []
    for n, run in enumerate(runs):
        label = 'with context loss' if n % 2 == 0 else 'no context loss'
        model = InferenceModel.load(run, expected_family=FAMILY)
        meta = model.metadata
        for source in ('random policy', 'own policy'):
            wins = random_wins if source == 'random policy' else [
                windows_for(FAMILY, v, args.episodes, args.steps, 7, model) for v in values]
            zs = [latents(model, w) for w in wins]
            rho, learned, true = spearman_tasks(values, zs)
            rho_s = spearman_samples(values, zs)
            rows.append({'run': label, 'dir': run.name, 'alpha_psi': meta['config']['alpha_psi'],
                         'timesteps': meta['steps']['timestep'],
                         'env_steps': meta['steps']['env_steps'], 'windows': source,
                         'tasks': len(values), 'spearman_task_means': round(rho, 3),
                         'spearman_window_pairs': round(rho_s, 3),
                         'paper': 0.60 if meta['config']['alpha_psi'] > 0 else 0.23})
            print(rows[-1], flush=True)
            if source == 'random policy' and n < 2:
                plots.append((label, rho, learned, true))
    RESULTS.mkdir(parents=True, exist_ok=True)
    with open(RESULTS / 'figure4_spearman.csv', 'w', newline='') as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = ['# Figure 4 reproduction (cheetah-run-v0, Spearman of context vs true distances)',
             '', f'Tasks: all {len(values)} train values of Table 3 ({values}); the paper '
             'plots 8. Windows: full k=5 windows from '
             f'{args.episodes} episodes x {args.steps} steps per task. Task-level: L2 '
             'distance between per-task mean latents vs |c_i - c_j| over all task pairs. '
             'Window-level: 5000 random pairs of single windows from different tasks.', '',
             '| run | dir | alpha_psi | timesteps (env steps) | windows '
             '| Spearman (task means) | Spearman (window pairs) | paper |',
             '|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['run']} | {r['dir']} | {r['alpha_psi']} | {r['timesteps']} "
                     f"({r['env_steps']}) | {r['windows']} | {r['spearman_task_means']} | "
                     f"{r['spearman_window_pairs']} | {r['paper']} |")
    lines += ['', f'Mean over the {len(runs) // 2} seed(s), random-policy windows, task means:']
    for label in ('with context loss', 'no context loss'):
        vals = [r['spearman_task_means'] for r in rows
                if r['run'] == label and r['windows'] == 'random policy']
        lines.append(f'- {label}: {np.mean(vals):.3f} (per seed {vals})')
    lines += ['', 'Notes: both arms of a seed trained concurrently with the cpu profile '
              '(one torch thread each); seed 1 under a wall-clock limit (step counts differ '
              'slightly), seed 2 for a fixed 12000 timesteps; all far shorter than the paper '
              '(1.2M steps). With '
              "random-policy windows both encoders see identical inputs; with each run's own "
              'policy the states visited also differ per task, which inflates both '
              'correlations. Single windows are dominated by state variation (window-level '
              'correlation near 0); only the per-task averages rank like the true lengths.']
    (RESULTS / 'figure4_spearman.md').write_text('\n'.join(lines) + '\n')
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    for ax, (label, rho, learned, true) in zip(axes, plots, strict=True):
        ax.scatter(true, learned, s=12)
        ax.set_xlabel('|c_i - c_j| (torso length, m)')
        ax.set_ylabel('||psi_i - psi_j||')
        ax.set_title(f'{label}: Spearman {rho:.2f}')
    fig.tight_layout()
    fig.savefig(RESULTS / 'figure4_spearman.png', dpi=80)


if __name__ == '__main__':
    main()
