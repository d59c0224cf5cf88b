"""Copy the small result files of finished training runs into a results folder.

    python research/analysis/collect_runs.py research/results/cheetah_v1_50k /work/runs/cv1-*

For each run directory: the trainer's logs (train_log.csv, eval_log.csv), the
adaptation report (adaptation.json / .txt, if it was run) and run.json, the
part of the checkpoint's metadata that says how the run was made (config,
steps and wall time, run arguments, code commit). Not the replay buffer or
the training state: results folders are committed, run folders are not (and
are lost with the machine they trained on). With `--with-weights` also the
inference weights (`checkpoint/model.safetensors` + `metadata.json`, about
0.8 MB for a cheetah), so that later analyses (Figure 4, a newer adaptation
report) can read the run from the committed folder:
`python -m zeus_ros.learning_tools.adaptation --weights research/results/<folder>/<run>`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import shutil
import sys

from zeus_ros.deploy.checkpoint import load_metadata, METADATA_FILE, MODEL_FILE
from zeus_ros.deploy.metadata import as_json, CheckpointMetadata

RESULT_FILES = ('train_log.csv', 'eval_log.csv', 'adaptation.json', 'adaptation.txt')
WEIGHT_FILES = (MODEL_FILE, METADATA_FILE)   # what InferenceModel.load reads


def collect(run: Path, into: Path, with_weights: bool = False) -> list[str]:
    """Copy one run's result files into `into/<run name>`; return what was copied."""
    meta_path = run / 'checkpoint' / METADATA_FILE
    if not meta_path.exists():
        raise FileNotFoundError(f'{run} has no checkpoint/metadata.json')
    target = into / run.name
    target.mkdir(parents=True, exist_ok=True)
    copied = []
    for name in RESULT_FILES:
        if (run / name).exists():
            shutil.copy2(run / name, target / name)
            copied.append(name)
    (target / 'run.json').write_text(json.dumps(run_record(load_metadata(run / 'checkpoint')),
                                                indent=2))
    copied.append('run.json')
    if with_weights:
        (target / 'checkpoint').mkdir(exist_ok=True)
        for name in WEIGHT_FILES:
            shutil.copy2(run / 'checkpoint' / name, target / 'checkpoint' / name)
        copied.append('checkpoint/')
    return copied


def run_record(meta: CheckpointMetadata) -> dict:
    """Return the part of the metadata that says how the run was made (run.json)."""
    return {'config': meta.config, 'steps': as_json(meta.steps), 'run': as_json(meta.run),
            'git_commit': meta.git_commit}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('into', type=Path, help='results folder')
    p.add_argument('runs', type=Path, nargs='+', help='run directories')
    p.add_argument('--with-weights', action='store_true',
                   help='also copy the inference weights (checkpoint/, no training state)')
    args = p.parse_args(argv)
    for run in args.runs:
        try:
            print(f'{run.name}: {", ".join(collect(run, args.into, args.with_weights))}')
        except FileNotFoundError as error:
            print(f'skipped: {error}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
