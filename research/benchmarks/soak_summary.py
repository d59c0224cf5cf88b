"""Summarise a series of soaks (soak_series.sh's OUT_DIR): one row per run, the passes in a row.

    python research/benchmarks/soak_summary.py research/results/soak_series_39 [--out FILE.md]

Reads run_<i>.json (soak.py --json) and run_<i>.txt (the series' header: load
and trainings beside the run, counted at its start and, in later series, at its
end). A run without its JSON did not finish (the series was stopped): listed,
not counted. Prints Markdown.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
import json
from pathlib import Path
import re


@dataclass(frozen=True)
class SoakRun:
    index: int
    passed: bool | None               # None: no figures (the run did not finish)
    trainings: int | None             # beside the run at its start
    trainings_at_end: int | None      # None: not recorded (series before the end count)
    load_before: str
    restarts_s: dict[str, float | None]   # control back after the start-up line, per node
    failed: tuple[str, ...]
    steps_per_s: float | None
    uncontrolled_steps: int | None
    swaps: str


def _header(text: str, key: str) -> str:
    found = re.search(rf'^{key}: (.*)$', text, re.MULTILINE)
    return found.group(1).strip() if found else ''


def _count(text: str, key: str) -> int | None:
    value = _header(text, key)
    return int(value) if value.isdigit() else None


def _trainings(run: SoakRun) -> str:
    return str(run.trainings) if run.trainings_at_end is None \
        else f'{run.trainings} / {run.trainings_at_end}'


def read_run(out_dir: Path, index: int) -> SoakRun:
    header = (out_dir / f'run_{index}.txt').read_text()
    figures = out_dir / f'run_{index}.json'
    common = {'index': index, 'trainings': _count(header, 'trainings beside it'),
              'trainings_at_end': _count(header, 'trainings beside it at the end'),
              'load_before': _header(header, 'load before')}
    if not figures.is_file():
        return SoakRun(passed=None, restarts_s={}, failed=(), steps_per_s=None,
                       uncontrolled_steps=None, swaps='', **common)
    result = json.loads(figures.read_text())
    swaps = result['swaps']
    return SoakRun(
        passed=result['passed'],
        restarts_s={r['node']: r['control_back_after_startup_s'] for r in result['restarts']
                    if r['cause'] == 'soak'},
        failed=tuple(g['name'] for g in result['goals'] if not g['met']),
        steps_per_s=round(result['steps_total'] / result['duration_s'], 1),
        uncontrolled_steps=result['uncontrolled_steps'],
        swaps=f"{swaps['accepted']}/{swaps['requested']} accepted, {swaps['unanswered']} "
              'unanswered', **common)


def passes_in_a_row(runs: list[SoakRun]) -> int:
    """Return the longest run of consecutive passes (an unfinished run breaks none)."""
    best = current = 0
    for run in runs:
        if run.passed is None:
            continue
        current = current + 1 if run.passed else 0
        best = max(best, current)
    return best


def _seconds(value: float | None) -> str:
    return 'never' if value is None else f'{value:.2f}'


def table(runs: list[SoakRun]) -> list[str]:
    lines = ['| run | result | trainings beside (start / end) | load before (1/5/15 min) | '
             'control back after start-up, s (sim / context / policy) | steps/s | '
             'uncontrolled steps | swaps | goals missed |',
             '|---|---|---|---|---|---|---|---|---|']
    for run in runs:
        if run.passed is None:
            lines.append(f'| {run.index} | not finished | {_trainings(run)} | {run.load_before} '
                         '| - | - | - | - | - |')
            continue
        back = ' / '.join(_seconds(run.restarts_s.get(node))
                          for node in ('sim_node', 'context_node', 'policy_node'))
        lines.append(f'| {run.index} | {"PASS" if run.passed else "FAIL"} | {_trainings(run)} | '
                     f'{run.load_before} | {back} | {run.steps_per_s} | '
                     f'{run.uncontrolled_steps} | {run.swaps} | '
                     f'{"; ".join(run.failed) or "-"} |')
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('out_dir', type=Path, help="soak_series.sh's OUT_DIR")
    parser.add_argument('--out', type=Path, help='also write the Markdown here')
    args = parser.parse_args(argv)
    indices = sorted(int(p.stem.split('_')[1]) for p in args.out_dir.glob('run_*.txt'))
    runs = [read_run(args.out_dir, i) for i in indices]
    finished = [r for r in runs if r.passed is not None]
    backs = [b for r in finished for b in r.restarts_s.values() if b is not None]
    lines = [f'Soaks in {args.out_dir}: {len(finished)} finished, '
             f'{sum(bool(r.passed) for r in finished)} passed, '
             f'{passes_in_a_row(runs)} in a row; restarts: control back within 2 s of the '
             f'start-up line in {sum(b <= 2.0 for b in backs)} of '
             f'{sum(len(r.restarts_s) for r in finished)}.', '', *table(runs)]
    text = '\n'.join(lines) + '\n'
    print(text, end='')
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
