"""Copy a run's deployable weights into weights/ with their evaluation record.

    python scripts/ship_weights.py runs/walker-walk-v0-zeus weights/walker-walk-v0-zeus \
        --command "python -m zeus_ros.learning_tools.train ..." --episodes 2

Copies model.safetensors and metadata.json (what the nodes load; the training
state with the replay buffer stays in the run), evaluates the checkpoint on the
train, interpolation and extrapolation values with `zeus_ros.learning_tools.evaluate` and
writes RECORD.md and record.json beside the weights.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
import shutil
import time

import numpy as np

from sim_node.families import format_task, get_sim_family, SPLITS
from zeus_ros.learning_tools.adaptation import build_report, ReportConfig
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.deploy.metadata import as_json
from zeus_ros.learning_tools.evaluate import evaluate

SHIPPED = ('model.safetensors', 'metadata.json')


def training_wall_time(run: Path) -> float | None:
    """Training wall time in seconds from the run's train_log.csv (last row)."""
    log = run / 'train_log.csv'
    if not log.exists():
        return None
    with open(log, newline='') as handle:
        rows = list(csv.DictReader(handle))
    return float(rows[-1]['wall_s']) if rows else None


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('run', type=Path)
    parser.add_argument('dest', type=Path)
    parser.add_argument('--command', required=True, help='the training command, verbatim')
    parser.add_argument('--episodes', type=int, default=2, help='evaluation episodes per value')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--note', default='', help='a line for the record')
    parser.add_argument('--no-report', action='store_true',
                        help='skip the adaptation report (zeus_ros.learning_tools.adaptation)')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    args.dest.mkdir(parents=True, exist_ok=True)
    for name in SHIPPED:
        shutil.copyfile(args.run / 'checkpoint' / name, args.dest / name)
    model = InferenceModel.load(args.dest)
    record = build_record(args, model)
    if not args.no_report:
        report = build_report(str(args.dest), ReportConfig(episodes=args.episodes))
        (args.dest / 'adaptation.json').write_text(report.to_json())
        record['adaptation_report'] = 'adaptation.json'
    (args.dest / 'record.json').write_text(json.dumps(record, indent=2))
    lines = record_lines(args, model, record)
    (args.dest / 'RECORD.md').write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))
    return 0


def build_record(args: argparse.Namespace, model: InferenceModel) -> dict:
    """Evaluate the shipped copy on every split and gather what the record says of it."""
    spec = get_sim_family(model.family)
    started = time.monotonic()
    results = {split: evaluate(model, spec.split(split), args.episodes, args.seed)
               for split in SPLITS if spec.split(split)}
    meta = model.meta
    return {
        'family': model.family, 'method': model.method_name, 'command': args.command,
        'seed': meta.seed,
        'steps': as_json(meta.steps),
        'training_wall_s': meta.steps.wall_s or training_wall_time(args.run),
        'alpha_psi': meta.zeus_config().alpha_psi, 'git_commit': meta.git_commit,
        'eval_episodes_per_value': args.episodes, 'eval_seed': args.seed,
        'eval_wall_s': time.monotonic() - started, 'results': results,
        'size_bytes': {n: (args.dest / n).stat().st_size for n in SHIPPED},
        'note': args.note,
    }


def record_lines(args: argparse.Namespace, model: InferenceModel, record: dict) -> list[str]:
    """RECORD.md: the run's provenance, then a table per split."""
    spec = get_sim_family(model.family)
    lines = [f'# {args.dest.name}', '', f'- family: `{model.family}` '
             f'({", ".join(spec.param_names)}), method `{record["method"]}`, '
             f'seed {record["seed"]}, '
             f'alpha_psi = {record["alpha_psi"]}',
             f'- command: `{args.command}`',
             f'- steps: {record["steps"]}',
             f'- training wall time: {record["training_wall_s"]:.0f} s on a 2-core CPU'
             if record['training_wall_s'] else '- training wall time: unknown',
             '- files: ' + ', '.join(f'{n} ({s / 1e3:.0f} kB)'
                                      for n, s in record['size_bytes'].items()),
             '- evaluation: `zeus_ros.learning_tools.evaluate`, deterministic policy, '
             f'{args.episodes} '
             f'episode(s) per value, seeds {args.seed}..{args.seed + args.episodes - 1}', '']
    if args.note:
        lines += [args.note, '']
    return lines + _result_tables(record['results'])


def _result_tables(results: dict) -> list[str]:
    """Per-value and per-split tables; a success column where the task has a success flag."""
    success = any(r['success_rate'] is not None for rows in results.values() for r in rows)
    extra = (' success rate |', '---|') if success else ('', '')
    lines = ['| split | value | mean return | std | mean decoded estimate |' + extra[0],
             '|---|---|---|---|---|' + extra[1]]
    for split, rows in results.items():
        for row in rows:
            estimate = ' '.join(f'{v:.3f}' for v in np.atleast_1d(row['mean_estimate']))
            tail = f' {row["success_rate"]:.2f} |' if success else ''
            lines.append(f'| {split} | {format_task(row["value"])} | {row["mean_return"]:.1f} | '
                         f'{row["std_return"]:.1f} | {estimate} |{tail}')
    lines += ['', '| split | mean return over values |' + extra[0], '|---|---|' + extra[1]]
    for split, rows in results.items():
        tail = f' {np.mean([r["success_rate"] for r in rows]):.2f} |' if success else ''
        lines.append(f'| {split} | {np.mean([r["mean_return"] for r in rows]):.1f} |{tail}')
    return lines


if __name__ == '__main__':
    raise SystemExit(main())
