"""Tabulate committed adaptation reports over training seeds (mean +- standard error).

    PYTHONPATH=. python repro/summarize_runs.py repro/results/cheetah_v1_50k [--curves PNG]

Runs are grouped by folder name without its seed suffix (`cv1-zeus-s2` ->
`cv1-zeus`, `cv1-zeus-id-swap-s1` -> `cv1-zeus-id-swap`); each row reads the
`adaptation.json` that `python -m zeus_ros.adaptation --json` wrote for the
run (folders without one are listed as missing, not averaged). The README's
adaptation tables are this script's output on the committed folders. With
`--curves`, the groups' learning curves from each run's eval_log.csv (mean
over seeds, shaded standard error, one panel per split, as Figure 2).
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from dataclasses import dataclass
import json
from pathlib import Path
import re
import sys

from zeus_ros.sweep_results import (mean_sem_cell, plot_groups, read_curve, SWAP_STEPS,
                                    swaps_covered)

SEED_SUFFIX = re.compile(r'-s(\d+)$')


@dataclass(frozen=True)
class RunFigures:
    """What one run's adaptation report says, as the table's columns read it."""

    seed: int
    train_return: float
    interpolation_return: float
    extrapolation_return: float | None   # families with an extrapolation split
    speed_error: float | None     # interpolation, reward-varying families only
    r2: float | None              # decoded estimate on held-out values; None without a latent
    largest_gap: float | None     # return lost when the context is perturbed
    success: tuple[float | None, float | None] = (None, None)   # train, interpolation
    largest_gap_train: float | None = None   # the same at the train values (newer reports)
    swaps_covered: float | None = None   # share of live swaps covered in time


def read_run(folder: Path) -> RunFigures:
    """Read one run's adaptation.json."""
    report = json.loads((folder / 'adaptation.json').read_text())
    returns = {r['split']: r['mean'] for r in report['returns']}
    success = {r['split']: r.get('success_rate') for r in report['returns']}
    velocity = report.get('velocity_error') or {}
    identification = report.get('identification') or {}
    use = report.get('context_use') or {}
    return RunFigures(
        seed=int(SEED_SUFFIX.search(folder.name).group(1)),
        train_return=returns['train'], interpolation_return=returns['interpolation'],
        extrapolation_return=returns.get('extrapolation'),
        speed_error=velocity.get('mean_per_split', {}).get('interpolation'),
        r2=identification.get('r2_per_step'), largest_gap=use.get('largest_gap'),
        success=(success.get('train'), success.get('interpolation')),
        largest_gap_train=(report.get('context_use_train') or {}).get('largest_gap'),
        swaps_covered=swaps_covered(report.get('swaps') or []))


def mean_se(values: list[float | None], digits: int) -> str:
    """'mean +- standard error' of what was measured; the mean for one value, '-' for none."""
    values = [v for v in values if v is not None]
    return f'{values[0]:.{digits}f}' if len(values) == 1 else mean_sem_cell(values, digits)


def table(results: Path) -> str:
    """Markdown table, one row per run group, in folder-name order."""
    groups: dict[str, list[RunFigures]] = defaultdict(list)
    missing: list[str] = []
    for folder in sorted(p for p in results.iterdir() if p.is_dir()):
        if not SEED_SUFFIX.search(folder.name):
            continue
        if not (folder / 'adaptation.json').exists():
            missing.append(folder.name)
            continue
        groups[SEED_SUFFIX.sub('', folder.name)].append(read_run(folder))
    # Success-rate columns only for tasks with a success flag (Sawyer-Peg-v0).
    with_success = any(r.success != (None, None) for runs in groups.values() for r in runs)
    # Context use at the train values only where some report measured it.
    with_train_gap = any(r.largest_gap_train is not None
                         for runs in groups.values() for r in runs)
    with_swaps = any(r.swaps_covered is not None for runs in groups.values() for r in runs)
    lines = ['| runs | seeds | train return | interpolation return | extrapolation return | '
             'interp. \\|speed - target\\| (m/s) | decoded R^2 (held-out) | '
             + (f'live swaps 70 % covered within {SWAP_STEPS} steps | ' if with_swaps else '')
             + 'largest return lost, context perturbed |'
             + (' the same at the train values |' if with_train_gap else '')
             + (' success, train | success, interpolation |' if with_success else ''),
             '|---|---|---|---|---|---|---|---|' + ('---|' if with_swaps else '')
             + ('---|' if with_train_gap else '') + ('---|---|' if with_success else '')]
    for name, runs in groups.items():
        runs.sort(key=lambda r: r.seed)
        cells = [f'| {name}', ', '.join(str(r.seed) for r in runs),
                 mean_se([r.train_return for r in runs], 0),
                 mean_se([r.interpolation_return for r in runs], 0),
                 mean_se([r.extrapolation_return for r in runs], 0),
                 mean_se([r.speed_error for r in runs], 2),
                 mean_se([r.r2 for r in runs], 2)]
        if with_swaps:
            cells.append(mean_se([r.swaps_covered for r in runs], 2))
        cells.append(mean_se([r.largest_gap for r in runs], 0))
        if with_train_gap:
            cells.append(mean_se([r.largest_gap_train for r in runs], 0))
        if with_success:
            cells += [mean_se([r.success[i] for r in runs], 2) for i in (0, 1)]
        lines.append(' | '.join(cells) + ' |')
    if missing:
        lines.append(f'\n(no adaptation report yet: {", ".join(missing)})')
    return '\n'.join(lines)


def plot(results: Path, path: Path) -> Path:
    """Learning curves of every run group in the folder ({group: {seed: Curve}})."""
    groups: dict[str, dict] = defaultdict(dict)
    for folder in sorted(p for p in results.iterdir() if p.is_dir()):
        seed = SEED_SUFFIX.search(folder.name)
        curve = read_curve(folder / 'eval_log.csv') if seed else None
        if curve is not None:
            groups[SEED_SUFFIX.sub('', folder.name)][int(seed.group(1))] = curve
    return plot_groups(results.name, dict(groups), path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('results', type=Path, help='a folder of collected runs (collect_runs.py)')
    parser.add_argument('--curves', type=Path, metavar='PNG',
                        help='also draw the learning curves of every run group into PNG')
    args = parser.parse_args(argv)
    print(table(args.results))
    if args.curves:
        print(f'curves: {plot(args.results, args.curves)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
