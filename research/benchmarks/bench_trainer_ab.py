"""Trainer speed, this tree against an older commit, side by side in one run.

    python research/benchmarks/bench_trainer_ab.py --baseline ad864f5 --rounds 3 --threads 1

Checks the baseline out into a temporary git worktree and runs
`research/benchmarks/bench_trainer.py` of each tree (in commits from before
the research/ folder, the same script in a top-level benchmarks folder) in
turn (A B A B ..., so that both see the same machine in the same minutes),
with the same family, profile, method, timesteps and torch threads; prints
each run's environment steps per second, the medians and the ratio new /
old. Only the options the baseline's bench_trainer already had are passed to
it (`--set` goes to the new tree only, to try a setting before it becomes
the profile's).

`--pair` then runs two copies of the new tree at once, one thread each (the
setting when two trainings share the 2 cores), and reports each one's rate
against the new tree's own median alone: how much two runs slow each other
beyond what the cores explain. Nothing else may run meanwhile: the figures
are rates on a shared 2-core machine.
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

REPO = Path(__file__).resolve().parents[2]
# Where bench_trainer.py lives in a tree: here, or in a commit from before the research/
# folder, in the benchmarks folder at the top.
TRAINER_SCRIPTS = (Path('research', 'benchmarks', 'bench_trainer.py'),
                   Path('bench', 'bench_trainer.py'))
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


def trainer_script(tree: Path) -> Path:
    """Return the tree's bench_trainer.py, relative to the tree."""
    for script in TRAINER_SCRIPTS:
        if (tree / script).exists():
            return script
    raise SystemExit(f'the tree at {tree} has no bench_trainer.py')


def bench_command(tree: Path, args, new: bool) -> tuple[list, dict]:
    """Build the bench_trainer command line and environment for one tree."""
    script = trainer_script(tree)
    cmd = [sys.executable, str(script), '--family', args.family, '--profile',
           args.profile, '--timesteps', str(args.timesteps), '--threads', str(args.threads)]
    if args.method != 'zeus':   # before the plug-ins (884b5ea) every run was zeus
        if "'--method'" not in (tree / script).read_text():
            raise SystemExit(f'the tree at {tree} trains zeus only: compare --method zeus')
        cmd += ['--method', args.method]
    if new and args.set:
        cmd += ['--set', *args.set]
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS=str(args.threads))
    return cmd, env


def parse_rate(tree: Path, out: subprocess.CompletedProcess) -> float:
    match = RATE.search(out.stdout)
    if out.returncode != 0 or match is None:
        raise RuntimeError(f'no rate from {tree}:\n{out.stdout}\n{out.stderr}')
    return float(match.group(1))


def one_run(tree: Path, args, new: bool) -> float:
    """Return the environment steps/s of the tree's bench_trainer (its first figure line)."""
    cmd, env = bench_command(tree, args, new)
    return parse_rate(tree, subprocess.run(cmd, cwd=tree, env=env, capture_output=True,
                                           text=True))


def pair_run(tree: Path, args) -> list[float]:
    """Two copies of the new tree's bench at once; their rates."""
    cmd, env = bench_command(tree, args, new=True)
    procs = [subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    rates = []
    for proc in procs:
        stdout, stderr = proc.communicate()
        rates.append(parse_rate(tree, subprocess.CompletedProcess(
            proc.args, proc.returncode, stdout, stderr)))
    return rates


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--baseline', default='ad864f5', help='commit to compare against')
    p.add_argument('--family', default='walker-walk-slippery')
    p.add_argument('--profile', default='cpu')
    p.add_argument('--method', default='zeus')
    p.add_argument('--timesteps', type=int, default=300)
    p.add_argument('--threads', type=int, default=1)
    p.add_argument('--rounds', type=int, default=3)
    p.add_argument('--set', nargs='*', default=[], metavar='KEY=VALUE',
                   help='config overrides for the NEW tree only')
    p.add_argument('--pair', action='store_true',
                   help='also run two copies of the new tree at once')
    p.add_argument('--json', type=Path, default=None)
    args = p.parse_args(argv)
    old_tree = worktree(args.baseline)
    rates = {'old': [], 'new': []}
    try:
        for _ in range(args.rounds):
            rates['old'].append(one_run(old_tree, args, new=False))
            rates['new'].append(one_run(REPO, args, new=True))
            print(f"old {rates['old'][-1]:.0f}  new {rates['new'][-1]:.0f} env steps/s")
    finally:
        drop_worktree(old_tree)
    medians = {k: statistics.median(v) for k, v in rates.items()}
    ratio = medians['new'] / medians['old']
    label = f"{args.family} {args.method} {args.profile} {' '.join(args.set)}".strip()
    print(f"{label}, {args.threads} thread(s): old ({args.baseline}) "
          f"{medians['old']:.0f}, new {medians['new']:.0f} env steps/s (medians of "
          f"{args.rounds}); new / old = {ratio:.2f}")
    result = {'baseline': args.baseline, 'family': args.family, 'method': args.method,
              'profile': args.profile, 'set': args.set, 'threads': args.threads,
              'rates': rates, 'medians': medians, 'ratio': ratio}
    if args.pair:
        pair = pair_run(REPO, args)
        result['pair'] = {'rates': pair, 'alone': medians['new'],
                          'each_over_alone': [r / medians['new'] for r in pair]}
        print(f'two at once, one thread each: {pair[0]:.0f} and {pair[1]:.0f} env steps/s = '
              + ' and '.join(f'{r / medians["new"]:.2f}' for r in pair)
              + ' of one alone')
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
