"""Plot learning curves and per-split results from training logs.

    python scripts/training_plots.py runs/walker-walk-v0-zeus [runs/other ...] --out weights/plots

For each run: the training-episode return per task against environment steps
(from episodes.csv) and the evaluation return per split (eval_log.csv); and,
for the last evaluation, the return per parameter value, one bar per run.
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.figure import Figure

SPLIT_COLOURS = {'train': 'tab:blue', 'interpolation': 'tab:green',
                 'extrapolation': 'tab:red'}


def read_csv(path: Path) -> list[dict]:
    with open(path, newline='') as handle:
        return list(csv.DictReader(handle))


def smooth(values: np.ndarray, width: int) -> np.ndarray:
    if len(values) < width:
        return values
    return np.convolve(values, np.ones(width) / width, mode='valid')


def save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def learning_curves(runs: list[Path], out: Path) -> Path:
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for run in runs:
        # All training tasks end an episode on the same timestep: one point each.
        per_timestep = defaultdict(list)
        for row in read_csv(run / 'episodes.csv'):
            per_timestep[int(row['timestep'])].append((float(row['env_steps']),
                                                        float(row['return'])))
        points = [np.mean(v, axis=0) for _, v in sorted(per_timestep.items())]
        steps, returns = np.array(points).T if points else (np.array([]), np.array([]))
        width = 4
        axes[0].plot(steps[width - 1:] if len(steps) >= width else steps,
                     smooth(returns, width), label=run.name)
        by_split = defaultdict(lambda: defaultdict(list))
        for row in read_csv(run / 'eval_log.csv'):
            by_split[row['split']][float(row['env_steps'])].append(float(row['return']))
        for split, points in by_split.items():
            xs = sorted(points)
            axes[1].plot(xs, [np.mean(points[x]) for x in xs], marker='o',
                         color=SPLIT_COLOURS.get(split), label=f'{run.name}: {split}',
                         linestyle='-' if run == runs[0] else '--')
    axes[0].set_title('training episodes (mean over tasks, moving mean of 4)')
    axes[1].set_title("evaluation (mean over the split's values)")
    for ax in axes:
        ax.set_xlabel('environment steps (all tasks)')
        ax.set_ylabel('episode return')
        ax.legend(fontsize=7)
    return save(fig, out / 'learning_curves.png')


def final_eval(runs: list[Path], out: Path) -> Path:
    fig, ax = plt.subplots(figsize=(12, 4.5))
    width = 0.8 / len(runs)
    labels = None
    for i, run in enumerate(runs):
        rows = read_csv(run / 'eval_log.csv')
        last = max(float(r['env_steps']) for r in rows)
        rows = [r for r in rows if float(r['env_steps']) == last]
        # The value as the log wrote it: '0.8', or '0.44 -0.07' for several parameters.
        labels = [f'{r["split"][:5]}\n{r["value"]}' for r in rows]
        colours = [SPLIT_COLOURS.get(r['split']) for r in rows]
        ax.bar(np.arange(len(rows)) + i * width, [float(r['return']) for r in rows], width,
               color=colours, alpha=1.0 - 0.4 * i,
               label=f'{run.name} ({int(last)} env steps)')
    ax.set_xticks(np.arange(len(labels)) + width * (len(runs) - 1) / 2, labels, fontsize=7)
    ax.set_ylabel('return (last evaluation)')
    ax.legend(fontsize=8)
    return save(fig, out / 'final_eval_per_value.png')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('runs', nargs='+', type=Path, help='run directories')
    parser.add_argument('--out', type=Path, required=True)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    print(learning_curves(args.runs, args.out))
    print(final_eval(args.runs, args.out))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
