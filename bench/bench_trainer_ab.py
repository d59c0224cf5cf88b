"""Trainer speed, this tree against an older commit, side by side in one run.

    python bench/bench_trainer_ab.py --baseline ad864f5 --rounds 3 --threads 1

Checks the baseline out into a temporary git worktree and runs
`bench/bench_trainer.py` of each tree in turn (A B A B ..., so that both see
the same machine in the same minutes), with the same family, profile,
timesteps and torch threads; prints each run's environment steps per second,
the medians and the ratio new / old. Only the options the baseline's
bench_trainer already had are passed. Nothing else may run meanwhile: the
figure is a rate on a shared 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import re
import statistics
import subprocess
import sys
import tempfile

REPO = Path(__file__).resolve().parents[1]
RATE = re.compile(r'= (\d+) env steps/s')


def worktree(rev: str) -> Path:
    """Check `rev` out, detached, into a temporary folder (removed by `drop_worktree`)."""
    path = Path(tempfile.mkdtemp(prefix='zeus_ab_'))
    subprocess.run(['git', '-C', str(REPO), 'worktree', 'add', '--detach', str(path), rev],
                   check=True, capture_output=True)
    return path


def drop_worktree(path: Path) -> None:
    subprocess.run(['git', '-C', str(REPO), 'worktree', 'remove', '--force', str(path)],
                   capture_output=True)


def one_run(tree: Path, args) -> float:
    """Return the environment steps/s of the tree's bench_trainer (its first figure line)."""
    cmd = [sys.executable, 'bench/bench_trainer.py', '--family', args.family, '--profile',
           args.profile, '--timesteps', str(args.timesteps), '--threads', str(args.threads)]
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS=str(args.threads))
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=True)
    match = RATE.search(out.stdout)
    if match is None:
        raise RuntimeError(f'no rate in the output of {tree}:\n{out.stdout}\n{out.stderr}')
    return float(match.group(1))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--baseline', default='ad864f5', help='commit to compare against')
    p.add_argument('--family', default='walker-walk-slippery')
    p.add_argument('--profile', default='cpu')
    p.add_argument('--timesteps', type=int, default=300)
    p.add_argument('--threads', type=int, default=1)
    p.add_argument('--rounds', type=int, default=3)
    p.add_argument('--json', type=Path, default=None)
    args = p.parse_args(argv)
    old_tree = worktree(args.baseline)
    rates = {'old': [], 'new': []}
    try:
        for _ in range(args.rounds):
            rates['old'].append(one_run(old_tree, args))
            rates['new'].append(one_run(REPO, args))
            print(f"old {rates['old'][-1]:.0f}  new {rates['new'][-1]:.0f} env steps/s")
    finally:
        drop_worktree(old_tree)
    medians = {k: statistics.median(v) for k, v in rates.items()}
    ratio = medians['new'] / medians['old']
    print(f"{args.family} {args.profile}, {args.threads} thread(s): old ({args.baseline}) "
          f"{medians['old']:.0f}, new {medians['new']:.0f} env steps/s (medians of "
          f"{args.rounds}); new / old = {ratio:.2f}")
    if args.json:
        args.json.write_text(json.dumps({'baseline': args.baseline, 'rates': rates,
                                         'medians': medians, 'ratio': ratio}, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
