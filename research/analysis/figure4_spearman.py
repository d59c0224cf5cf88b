"""Reproduce Figure 4: rank correlation of learned context vs true parameter distances.

Trains two cheetah-run-v0 runs of the same length and seed, with the context
loss (alpha_psi = 1, Table 11) and without (alpha_psi = 0, the
ZeUS-no-context-loss ablation), or analyses existing runs of any method with a
learned latent (`--runs`: zeus, zeus-no-context-loss, zeus-id, cadm,
hyperdynamics, up-osi; privileged methods such as the oracle, whose latent is
the true parameter, are refused). For each run:

1. collects context windows in every training task (all 11 train values of
   Table 3; the paper's Figure 4 shows 8 tasks) from the SAME uniform-random
   trajectories for every run of one window length (so only the encoders
   differ) and, separately, from each run's own deterministic policy;
2. encodes each full window (the run's k) with the run's encoder, as the
   deployed context node does, and averages the latents per task;
3. computes the Spearman rank correlation between the pairwise L2 distances of
   the task latents and the pairwise |c_i - c_j| (55 pairs), and, as a
   sample-level check, over random pairs of single windows from different
   tasks.

Writes research/results/<name>.{csv,md,png} (--name, default figure4_spearman), with
the mean +- standard error over runs of each method.

    PYTHONPATH=. python research/analysis/figure4_spearman.py --train-minutes 20
    PYTHONPATH=. python research/analysis/figure4_spearman.py --name figure4_spearman_50k \
        --runs runs/cv0-zeus-s1 runs/cv0-zeus-no-context-loss-s1 ...   # existing runs
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
from zeus_ros.deploy.metadata import CheckpointMetadata
from zeus_ros.core.window import ContextWindow
from zeus_ros.learning_tools.sweep_results import mean_sem

FAMILY = 'cheetah-run-v0'
RESULTS = Path(__file__).resolve().parents[1] / 'results'
# Figure 4's values, read off the paper's plot, for the two methods it shows.
PAPER = {'zeus': 0.60, 'zeus-no-context-loss': 0.23}
WINDOW_SOURCES = ('random policy', 'own policy')


def windows_for(family, value, episodes, steps, seed, model=None, k=None):
    """Full k-windows (rows, mask) along trajectories; random policy if model is None.

    k: the window length (default: the model's, or 5 without a model).
    """
    k = k or (model.k if model is not None else 5)
    env = ParamEnv(family, value, seed=seed, episode_steps=steps)
    rng = np.random.default_rng(seed)
    out = []
    for e in range(episodes):
        obs = env.reset(seed=seed * 100 + e)
        w = ContextWindow(k, env.obs_dim, env.action_dim)
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
    """Return the deployed latent of each window, in one batch."""
    rows = torch.from_numpy(np.stack([r for r, _ in wins]).astype(np.float32))
    mask = torch.from_numpy(np.stack([m for _, m in wins]).astype(bool))
    with torch.no_grad():
        return model.method.deployed_context(rows, mask, None).numpy()


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
    from zeus_ros.learning_tools import train
    runs = []
    for alpha in (1.0, 0.0):
        out = Path('runs') / f'fig4-cheetah-alpha{alpha}'
        train.main(['--family', FAMILY, '--seed', str(seed), '--out', str(out),
                    '--alpha-psi', str(alpha), '--steps', '1000000',
                    '--time-limit', str(minutes), '--eval-every', '0',
                    '--no-save-replay', '--quiet', '--set', 'num_threads=1'])
        runs.append(out)
    return runs


def method_label(meta: CheckpointMetadata) -> str:
    """Name the method a run trained (zeus at alpha_psi = 0: the no-context-loss ablation)."""
    method = meta.context.method
    if method == 'zeus' and meta.zeus_config().alpha_psi == 0:
        return 'zeus-no-context-loss'
    return method


class RandomWindows:
    """The uniform-random windows of every train task, built once per window length."""

    def __init__(self, values, episodes, steps):
        self.values, self.episodes, self.steps = values, episodes, steps
        self._by_k: dict[int, list] = {}

    def __call__(self, k: int) -> list:
        if k not in self._by_k:
            self._by_k[k] = [windows_for(FAMILY, v, self.episodes, self.steps, 7, k=k)
                             for v in self.values]
        return self._by_k[k]


def analyse(run: Path, random_windows: RandomWindows) -> tuple[list[dict], tuple]:
    """One row per window source for a run, and its random-policy plot data."""
    model = InferenceModel.load(run, expected_family=FAMILY)
    if model.needs_true_param or model.context_dim == 0:
        raise SystemExit(f'{run}: {model.method_name} has no learned latent')
    meta, values = model.meta, random_windows.values
    label, rows, plot = method_label(meta), [], None
    for source in WINDOW_SOURCES:
        wins = random_windows(model.k) if source == 'random policy' else [
            windows_for(FAMILY, v, random_windows.episodes, random_windows.steps, 7, model)
            for v in values]
        zs = [latents(model, w) for w in wins]
        rho, learned, true = spearman_tasks(values, zs)
        rows.append({'method': label, 'dir': run.name, 'seed': meta.seed, 'k': model.k,
                     'alpha_psi': meta.zeus_config().alpha_psi,
                     'timesteps': meta.steps.timestep,
                     'env_steps': meta.steps.env_steps, 'windows': source,
                     'tasks': len(values), 'spearman_task_means': round(rho, 3),
                     'spearman_window_pairs': round(spearman_samples(values, zs), 3),
                     'paper': PAPER.get(label, '-')})
        print(rows[-1], flush=True)
        if source == 'random policy':
            plot = (f'{label} ({run.name})', rho, learned, true)
    return rows, plot


def summary_lines(rows: list[dict]) -> list[str]:
    """Per method: mean +- standard error over its runs, task means, each window source."""
    lines = ['| method | runs | Spearman, random-policy windows | own-policy windows | '
             'paper |', '|---|---|---|---|---|']
    for label in dict.fromkeys(r['method'] for r in rows):
        cells = []
        for source in WINDOW_SOURCES:
            vals = [r['spearman_task_means'] for r in rows
                    if r['method'] == label and r['windows'] == source]
            mean, sem = mean_sem(vals)
            cells.append(f'{mean:.2f} +- {sem:.2f} ({", ".join(f"{v:.2f}" for v in vals)})')
        lines.append(f'| {label} | {len(vals)} | {cells[0]} | {cells[1]} | '
                     f'{PAPER.get(label, "-")} |')
    return lines


def write_markdown(path: Path, rows: list[dict], values, episodes: int, steps: int) -> None:
    lines = ['# Figure 4 reproduction (cheetah-run-v0, Spearman of context vs true distances)',
             '', f'Tasks: all {len(values)} train values of Table 3 ({values}); the paper '
             "plots 8. Windows: full windows (each run's k) from "
             f'{episodes} episodes x {steps} steps per task. Task-level: L2 '
             'distance between per-task mean latents vs |c_i - c_j| over all task pairs. '
             'Window-level: 5000 random pairs of single windows from different tasks.', '',
             '| method | dir | seed | k | alpha_psi | timesteps (env steps) | windows '
             '| Spearman (task means) | Spearman (window pairs) | paper |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['method']} | {r['dir']} | {r['seed']} | {r['k']} | "
                     f"{r['alpha_psi']} | {r['timesteps']} ({r['env_steps']}) | "
                     f"{r['windows']} | {r['spearman_task_means']} | "
                     f"{r['spearman_window_pairs']} | {r['paper']} |")
    lines += ['', 'Per method, task means, mean +- standard error over runs (per run):', '',
              *summary_lines(rows), '',
              'With random-policy windows every encoder of one window length sees '
              "identical inputs; with each run's own policy the states visited also differ "
              'per task, which inflates the correlations. Single windows are dominated by '
              'state variation; the per-task averages are what Figure 4 ranks.']
    path.write_text('\n'.join(lines) + '\n')


def write_plot(path: Path, plots: list) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(plots), figsize=(4.5 * len(plots), 4), squeeze=False)
    for ax, (label, rho, learned, true) in zip(axes[0], plots, strict=True):
        ax.scatter(true, learned, s=12)
        ax.set_xlabel('|c_i - c_j| (torso length, m)')
        ax.set_ylabel('||psi_i - psi_j||')
        ax.set_title(f'{label}: Spearman {rho:.2f}', fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--runs', nargs='+', type=Path, default=None,
                   help='existing run (or checkpoint) dirs of cheetah-run-v0, any methods '
                        'with a learned latent; without it, trains the two-run pair')
    p.add_argument('--name', default='figure4_spearman',
                   help='output stem under research/results/ (.csv, .md, .png)')
    p.add_argument('--train-minutes', type=float, default=20.0)
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--episodes', type=int, default=2)
    p.add_argument('--steps', type=int, default=300)
    args = p.parse_args(argv)
    runs = args.runs or train_runs(args.train_minutes, args.seed)
    values = list(get_family(FAMILY).train)
    random_windows = RandomWindows(values, args.episodes, args.steps)
    rows, plots, plotted = [], [], set()
    for run in runs:
        found, plot = analyse(run, random_windows)
        rows += found
        if found[0]['method'] not in plotted:   # the first run of each method
            plotted.add(found[0]['method'])
            plots.append(plot)
    RESULTS.mkdir(parents=True, exist_ok=True)
    with open(RESULTS / f'{args.name}.csv', 'w', newline='') as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    write_markdown(RESULTS / f'{args.name}.md', rows, values, args.episodes, args.steps)
    write_plot(RESULTS / f'{args.name}.png', plots)


if __name__ == '__main__':
    main()
