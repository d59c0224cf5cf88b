"""Copy the small result files of finished training runs into a results folder.

    python scripts/collect_runs.py repro/results/cheetah_v1_50k /work/runs/cv1-*

For each run directory: the trainer's logs (train_log.csv, eval_log.csv), the
adaptation report (adaptation.json / .txt, if it was run) and run.json, the
part of the checkpoint's metadata that says how the run was made (config,
steps and wall time, run arguments, code commit). Not the weights or the
replay buffer: results folders are committed, run folders are not.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import shutil
import sys

RESULT_FILES = ('train_log.csv', 'eval_log.csv', 'adaptation.json', 'adaptation.txt')
RUN_KEYS = ('config', 'steps', 'run', 'git_commit')


def collect(run: Path, into: Path) -> list[str]:
    """Copy one run's result files into `into/<run name>`; return what was copied."""
    meta_path = run / 'checkpoint' / 'metadata.json'
    if not meta_path.exists():
        raise FileNotFoundError(f'{run} has no checkpoint/metadata.json')
    target = into / run.name
    target.mkdir(parents=True, exist_ok=True)
    copied = []
    for name in RESULT_FILES:
        if (run / name).exists():
            shutil.copy2(run / name, target / name)
            copied.append(name)
    meta = json.loads(meta_path.read_text())
    (target / 'run.json').write_text(json.dumps({k: meta.get(k) for k in RUN_KEYS}, indent=2))
    return [*copied, 'run.json']


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('into', type=Path, help='results folder')
    p.add_argument('runs', type=Path, nargs='+', help='run directories')
    args = p.parse_args(argv)
    for run in args.runs:
        try:
            print(f'{run.name}: {", ".join(collect(run, args.into))}')
        except FileNotFoundError as error:
            print(f'skipped: {error}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
