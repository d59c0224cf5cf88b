"""Live swaps inside one episode: what each method keeps of its return when the physics change.

Issue #36 asks for a friction or link-length swap that the robot adapts to.
This runs the demo's episode in process (the ROS episode equals it to the bit,
test_parity) under one swap schedule, for every run folder given and several
episode seeds, and reports the return per schedule segment (before the first
swap, between swaps, after the last), so a method that recovers after a swap
shows it in the segment that follows.

    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/live_swaps.py \
        --schedule 0:0.12,333:0.07,666:0.19 --episodes 10 \
        --runs research/results/pilots_36/rl-sac-s{1,2,3}/checkpoint \
               research/results/pilots_36/rl-rma-s1/checkpoint ... \
        --out research/results/live_swaps_36/reacher-length.md

Runs are grouped by their method (from the checkpoint metadata): each group's
row gives the mean over its runs of the per-run mean over episodes, +- the
standard error over runs.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
import sys

import numpy as np

from summarize_runs import mean_se   # its folder is on the path when the script runs
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode


@dataclass(frozen=True)
class RunFigures:
    """One run's mean over episodes: the return per segment and over the episode."""

    run: str
    method: str
    segments: tuple[float, ...]
    total: float
    episodes: tuple[float, ...]   # each episode's return, by episode seed
    decoded: tuple[float, ...]    # mean decoded parameter per segment (NaN: no decoder)


def parse_schedule(text: str) -> dict[int, float]:
    """`0:0.12,333:0.07` -> {0: 0.12, 333: 0.07}; step 0 must be given."""
    schedule = {}
    for item in text.split(','):
        step, value = item.split(':')
        schedule[int(step)] = float(value)
    if 0 not in schedule:
        raise SystemExit('the schedule must give the value at step 0')
    return dict(sorted(schedule.items()))


def run_label(model: InferenceModel) -> str:
    """Name a run by its method, window, recipe and whether it trained with swaps."""
    config = model.meta.config
    swaps = ', swaps in training' if config.get('train_swap_prob', 0.0) else ''
    if config.get('train_swap_prob', 0.0) not in (0.0, 0.004):   # the recipes' rate (RMA's)
        swaps += f' at {config["train_swap_prob"]:g}'
    # Recipes that differ in what training visits or how the parameter is read (#47).
    swaps += ', live span' if config.get('train_span') == 'live' else ''
    swaps += ', log parameter' if config.get('param_space') == 'log' else ''
    if model.method_name in ('sac', 'oracle'):   # no window: the context is none or the truth
        return model.method_name + (f' ({swaps[2:]})' if swaps else '')
    # rma's raw-parameter ablation is another recipe, not another seed of the same one.
    raw = ', raw extrinsics' if config.get('rma_latent') is False else ''
    return f'{model.method_name} (k={model.k}{swaps}{raw})'


def run_figures(path: Path, schedule: dict[int, float], episodes: int, seed: int,
                steps: int) -> RunFigures:
    """Mean segment and total returns of one run over `episodes` seeded episodes."""
    model = InferenceModel.load(path)
    # The demo's steps count from 1: a swap "from step s" is in force for the s-th
    # step, which run_episode indexes s - 1 (the demo's segments are 332, 333, 335
    # steps long). So the figures here are the demo's, to the bit.
    bounds = [0, *(s - 1 for s in schedule if s), steps]
    per_episode, decoded = [], []
    for e in range(episodes):
        rec = run_episode(model, model.family, schedule[0], seed + e,
                          swap_schedule={s - 1: v for s, v in schedule.items() if s},
                          max_steps=steps)
        rewards = np.asarray(rec.rewards, dtype=float)
        per_episode.append([rewards[a:b].sum() for a, b in pairwise(bounds)])
        # The demo's "decoded (mean)" column: does the estimate follow each swap?
        estimates = np.asarray(rec.estimates, dtype=float).reshape(len(rewards), -1)[:, 0]
        decoded.append([estimates[a:b].mean() for a, b in pairwise(bounds)])
    segments = np.mean(per_episode, axis=0)
    return RunFigures(str(path), run_label(model), tuple(float(s) for s in segments),
                      float(segments.sum()), tuple(float(sum(e)) for e in per_episode),
                      tuple(float(d) for d in np.mean(decoded, axis=0)))


def table(figures: list[RunFigures], schedule: dict[int, float]) -> str:
    """Markdown: one row per method, mean +- SE over its runs per segment."""
    heads = [f'from step {s} at {v:g}' for s, v in schedule.items()]
    decoded_heads = [f'decoded at {v:g}' for v in schedule.values()]
    lines = ['| method | runs | ' + ' | '.join(heads) + ' | episode | '
             + ' | '.join(decoded_heads) + ' |',
             '|---|---|' + '---|' * (2 * len(heads) + 1)]
    groups: dict[str, list[RunFigures]] = defaultdict(list)
    for f in figures:
        groups[f.method].append(f)
    for method, runs in sorted(groups.items()):
        cells = [mean_se([r.segments[i] for r in runs], 0) for i in range(len(heads))]
        decoded = [mean_se([r.decoded[i] for r in runs if not np.isnan(r.decoded[i])], 2)
                   for i in range(len(heads))]
        lines.append(f'| {method} | {len(runs)} | ' + ' | '.join(cells)
                     + f' | {mean_se([r.total for r in runs], 0)} | ' + ' | '.join(decoded)
                     + ' |')
    return '\n'.join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', nargs='+', type=Path, required=True,
                        help='checkpoint folders (metadata.json and model.safetensors)')
    parser.add_argument('--schedule', required=True, help='step:value swaps, from step 0')
    parser.add_argument('--episodes', type=int, default=10, help='episode seeds per run')
    parser.add_argument('--seed', type=int, default=0, help='first episode seed')
    parser.add_argument('--steps', type=int, default=1000, help='steps per episode')
    parser.add_argument('--out', type=Path, help='write the table (and the runs) here')
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    schedule = parse_schedule(args.schedule)
    figures = []
    for path in args.runs:
        figures.append(run_figures(path, schedule, args.episodes, args.seed, args.steps))
        print(f'{path}: {figures[-1].method} segments '
              f'{[round(s, 1) for s in figures[-1].segments]} total {figures[-1].total:.1f} '
              f'decoded {[round(d, 3) for d in figures[-1].decoded]}', flush=True)
    text = table(figures, schedule)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        runs = '\n'.join(f'- `{f.run}` ({f.method}): {f.total:.1f}; by episode seed from '
                         f'{args.seed}: {", ".join(f"{e:.0f}" for e in f.episodes)}; decoded '
                         f'per segment {", ".join(f"{d:.3g}" for d in f.decoded)}'
                         for f in figures)
        command = 'PYTHONPATH=. OMP_NUM_THREADS=1 python ' + ' '.join(
            ['research/analysis/live_swaps.py', *map(str, sys.argv[1:])] if argv is None
            else ['research/analysis/live_swaps.py', *argv])
        args.out.write_text(f'`{command}`\n\n{text}\n\nPer run (episode return, mean over '
                            f'{args.episodes} episodes):\n\n{runs}\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
