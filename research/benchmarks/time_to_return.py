"""Learning against time: when runs first reach a return, and their final returns.

    PYTHONPATH=. python research/benchmarks/time_to_return.py --runs runs/old/* --vs runs/new/* \
        --thresholds 600 900 --split train

Reads each run's `eval_log.csv` (one row per split and parameter value at
every periodic evaluation) and reports, per group of runs (`--runs` and
`--vs`, e.g. today's code and a candidate, 3 seeds each):

* the timestep, environment steps and training wall time at which the mean
  return over the split's values first reached each threshold;
* the final mean return per split (mean +- standard error over the runs), at
  the same number of environment steps for every run (the smallest final
  count among them), which is the equal-steps comparison.

Wall times are the runs' own (`wall_s`, across resumes): comparable only
between runs that trained under the same load. `--rate` converts
environment steps into minutes at a measured rate instead (e.g. the
2-thread rate of `bench_trainer.py` on a quiet machine).
"""

from __future__ import annotations

import argparse
import collections
import csv
import json
import math
from pathlib import Path
import statistics
import sys


def split_curve(run: Path, split: str) -> list[tuple[int, int, float | None, float]]:
    """(timestep, env_steps, wall_s or None, mean return over values) per evaluation."""
    by_time = collections.OrderedDict()
    with open(run / 'eval_log.csv', newline='') as f:
        for row in csv.DictReader(f):
            if row['split'] != split:
                continue
            key = (int(row['timestep']), int(row['env_steps']))
            wall = float(row['wall_s']) if row.get('wall_s') else None
            by_time.setdefault(key, [wall, []])[1].append(float(row['return']))
    return [(t, e, w, statistics.fmean(v)) for (t, e), (w, v) in sorted(by_time.items())]


def first_reaching(curve, threshold: float):
    """Return the first evaluation with a mean return >= threshold, or None."""
    return next((point for point in curve if point[3] >= threshold), None)


def mean_se(values) -> tuple[float, float]:
    """Mean and standard error (0 for a single value)."""
    values = list(values)
    mean = statistics.fmean(values)
    se = statistics.stdev(values) / math.sqrt(len(values)) if len(values) > 1 else 0.0
    return mean, se


def at_env_steps(curve, env_steps: int):
    """Return the last evaluation at or before `env_steps`."""
    return [point for point in curve if point[1] <= env_steps][-1]


def group_report(name: str, runs: list[Path], args) -> dict:
    """Threshold crossings per run and the equal-steps returns of one group."""
    curves = {run.name: {s: split_curve(run, s) for s in args.splits} for run in runs}
    crossings = {}
    for run, by_split in curves.items():
        curve = by_split[args.split]
        crossings[run] = {}
        for threshold in args.thresholds:
            point = first_reaching(curve, threshold)
            crossings[run][threshold] = None if point is None else {
                'timestep': point[0], 'env_steps': point[1], 'wall_s': point[2],
                'minutes_at_rate': point[1] / args.rate / 60 if args.rate else None}
    return {'name': name, 'runs': [r.name for r in runs], 'crossings': crossings,
            'curves': curves}


def equal_steps(groups: list[dict], splits) -> dict:
    """Mean +- s.e. per group and split at the smallest final env-step count of all runs."""
    finals = [c[s][-1][1] for g in groups for c in g['curves'].values() for s in splits]
    steps = min(finals)
    out = {'env_steps': steps}
    for g in groups:
        out[g['name']] = {s: mean_se(at_env_steps(c[s], steps)[3]
                                     for c in g['curves'].values()) for s in splits}
    return out


def print_report(groups: list[dict], same: dict, args) -> None:
    for g in groups:
        print(f"== {g['name']}: {', '.join(g['runs'])}")
        for run, by_threshold in g['crossings'].items():
            parts = []
            for threshold, point in by_threshold.items():
                if point is None:
                    parts.append(f'{threshold:g}: not reached')
                    continue
                wall = f", {point['wall_s'] / 60:.1f} min" if point['wall_s'] else ''
                rate = f", {point['minutes_at_rate']:.1f} min at {args.rate:g}/s" \
                    if point['minutes_at_rate'] else ''
                parts.append(f"{threshold:g}: timestep {point['timestep']} "
                             f"({point['env_steps']} env steps{wall}{rate})")
            print(f'  {run}: ' + '; '.join(parts))
    print(f"equal environment steps ({same['env_steps']}), mean +- s.e. over runs:")
    for g in groups:
        cells = ', '.join(f'{s} {m:.0f} +- {se:.0f}' for s, (m, se) in same[g['name']].items())
        print(f"  {g['name']}: {cells}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--runs', type=Path, nargs='+', required=True, help='first group')
    p.add_argument('--vs', type=Path, nargs='*', default=[], help='second group')
    p.add_argument('--names', nargs=2, default=['runs', 'vs'])
    p.add_argument('--thresholds', type=float, nargs='+', default=[600.0, 900.0])
    p.add_argument('--split', default='train', help='split the thresholds are read on')
    p.add_argument('--splits', nargs='+', default=['train', 'interpolation', 'extrapolation'],
                   help='splits of the equal-steps comparison')
    p.add_argument('--rate', type=float, default=None,
                   help='env steps/s to convert env steps into minutes')
    p.add_argument('--json', type=Path, default=None)
    args = p.parse_args(argv)
    groups = [group_report(args.names[0], args.runs, args)]
    if args.vs:
        groups.append(group_report(args.names[1], args.vs, args))
    same = equal_steps(groups, args.splits)
    print_report(groups, same, args)
    if args.json:
        for g in groups:
            g.pop('curves')
        args.json.write_text(json.dumps({'groups': groups, 'equal_steps': same,
                                         'rate': args.rate}, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
