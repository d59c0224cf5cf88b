"""Gather a sweep's runs into one comparison table and learning-curve plots.

Reads every run directory of a sweep (`zeus_ros.learning_tools.sweep_config.run_dir`): its
``eval_log.csv`` (the trainer's periodic evaluation: deterministic episodes
on fixed start states, one row per split and value) and, with
``with_report``, the adaptation report of its final checkpoint. Writes into
the sweep folder:

* ``comparison.csv``: one row per family, method and split: mean +- standard
  error over seeds of the final evaluation's mean return over the split's
  values, the number of seeds, and the timestep evaluated;
* ``comparison.md``: the same as Markdown tables, one per family, plus the
  report's figures (R^2 of the decoded estimate, largest return gap when the
  context is perturbed) where they were computed;
* ``curves_<family>.png``: return against environment steps per split, one
  line per method (mean over seeds, shaded standard error), as the paper's
  Figure 2 (extrapolation) and Figures 7-8 (train, interpolation).
"""

from __future__ import annotations

import csv
from dataclasses import asdict, dataclass, field
import json
from pathlib import Path
from typing import Callable, Sequence, TYPE_CHECKING

import numpy as np

from zeus_ros.learning_tools.sweep_config import run_dir, SweepConfig

if TYPE_CHECKING:
    from matplotlib.axes import Axes

SPLIT_ORDER = ('train', 'interpolation', 'extrapolation')


@dataclass(frozen=True)
class Curve:
    """Mean evaluation return per split at each evaluated timestep of one run."""

    env_steps: tuple[int, ...]
    timesteps: tuple[int, ...]
    returns: dict[str, tuple[float, ...]]


def read_curve(path: Path) -> Curve | None:
    """Read the run's evaluation curve from eval_log.csv (None before any evaluation)."""
    if not path.exists():
        return None
    by_step: dict[int, dict] = {}
    for row in csv.DictReader(open(path)):
        entry = by_step.setdefault(int(row['timestep']), {'env': int(row['env_steps'])})
        entry.setdefault(row['split'], []).append(float(row['return']))
    if not by_step:
        return None
    steps = sorted(by_step)
    splits = [s for s in SPLIT_ORDER if all(s in by_step[t] for t in steps)]
    return Curve(tuple(by_step[t]['env'] for t in steps), tuple(steps),
                 {s: tuple(float(np.mean(by_step[t][s])) for t in steps) for s in splits})


def mean_sem(values: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error of the mean (0 for a single value)."""
    v = np.asarray(values, float)
    sem = float(v.std(ddof=1) / np.sqrt(v.size)) if v.size > 1 else 0.0
    return float(v.mean()), sem


def gather(cfg: SweepConfig) -> dict:
    """{(family, method): {seed: Curve}} for every run that has evaluated."""
    out = {}
    for family in cfg.families:
        for method in cfg.methods:
            curves = {s: read_curve(run_dir(cfg, family, method, s) / 'eval_log.csv')
                      for s in cfg.seeds}
            out[(family, method)] = {s: c for s, c in curves.items() if c is not None}
    return out


def finished(run: Path, steps: int) -> bool:
    """Return whether a run's checkpoint has reached `steps` timesteps."""
    from zeus_ros.deploy.checkpoint import load_metadata, METADATA_FILE
    checkpoint = run / 'checkpoint'
    return (checkpoint / METADATA_FILE).exists() and \
        load_metadata(checkpoint).steps.timestep >= steps


def table_rows(curves: dict, is_finished: Callable[[str, str, int], bool]) -> list[dict]:
    """Last-evaluation rows of the finished runs (`is_finished(family, method, seed)`).

    Each row: family, method, split, mean, sem, seeds, timestep (of the last
    evaluation), and how many runs are still short of the budget (left out: a
    half-trained run's last evaluation is not a result).
    """
    rows = []
    for (family, method), runs in curves.items():
        done = {s: c for s, c in runs.items() if is_finished(family, method, s)}
        for split in SPLIT_ORDER:
            finals = [c.returns[split][-1] for c in done.values() if split in c.returns]
            if finals:
                mean, sem = mean_sem(finals)
                rows.append({'family': family, 'method': method, 'split': split,
                             'mean': round(mean, 1), 'sem': round(sem, 1),
                             'seeds': len(finals),
                             'timestep': min(c.timesteps[-1] for c in done.values()),
                             'unfinished': len(runs) - len(done)})
    return rows


@dataclass
class ReportFigures:
    """Adaptation-report figures of one family and method, one entry per seed."""

    split_returns: dict[str, list[float]]   # split -> mean return over its values, per seed
    r2: list[float]
    largest_gap: list[float]
    # the same at the train values (reports since context_use_train), per seed
    largest_gap_train: list[float] = field(default_factory=list)
    # target-velocity families: split -> mean |speed - target| (m/s), per seed
    velocity_error: dict[str, list[float]] = field(default_factory=dict)
    # tasks with a success flag (Sawyer-Peg-v0): split -> success rate, per seed
    success_rate: dict[str, list[float]] = field(default_factory=dict)
    # methods with a latent: share of the live swaps covered in time, per seed
    swaps_covered: list[float] = field(default_factory=list)


# Issue #14's swap-response target: 70 % of a live swap covered within 20 control steps.
SWAP_STEPS = 20


def swaps_covered(swaps: list[dict]) -> float | None:
    """Share of a report's live swaps 70 % covered within SWAP_STEPS; None if none ran."""
    if not swaps:
        return None
    steps = [s['steps_to_70pct'] for s in swaps]
    return sum(n is not None and n <= SWAP_STEPS for n in steps) / len(steps)


def run_report(run: Path, episodes: int, steps: int) -> dict | None:
    """Return the adaptation report of a finished run's checkpoint as JSON (cached beside it).

    None while the run has not reached `steps` timesteps (a report of a
    half-trained policy would enter the table as a result). A report newer
    than the checkpoint's metadata is reused: reports are slow, and a
    finished run's checkpoint does not change.
    """
    from zeus_ros.learning_tools.adaptation import build_report, ReportConfig
    meta, cached = run / 'checkpoint' / 'metadata.json', run / 'adaptation.json'
    if not finished(run, steps):
        return None
    if cached.exists() and cached.stat().st_mtime > meta.stat().st_mtime:
        return json.loads(cached.read_text())
    report = build_report(str(run / 'checkpoint'), ReportConfig(episodes=episodes))
    cached.write_text(report.to_json())
    return json.loads(report.to_json())


def adaptation_figures(cfg: SweepConfig, episodes: int = 2) -> dict:
    """{(family, method): ReportFigures} from each run's adaptation report."""
    out = {}
    for family in cfg.families:
        for method in cfg.methods:
            figures = ReportFigures({}, [], [])
            for seed in cfg.seeds:
                report = run_report(run_dir(cfg, family, method, seed), episodes, cfg.steps)
                if report is None:
                    continue
                for split in report['returns']:
                    figures.split_returns.setdefault(split['split'], []).append(split['mean'])
                    if split.get('success_rate') is not None:
                        figures.success_rate.setdefault(split['split'], []).append(
                            split['success_rate'])
                for split, error in (report.get('velocity_error') or {}).get(
                        'mean_per_split', {}).items():
                    figures.velocity_error.setdefault(split, []).append(error)
                if report['identification'] is not None:
                    figures.r2.append(report['identification']['r2_per_step'])
                    figures.largest_gap.append(report['context_use']['largest_gap'])
                covered = swaps_covered(report.get('swaps') or [])
                if covered is not None:
                    figures.swaps_covered.append(covered)
                if report.get('context_use_train') is not None:
                    figures.largest_gap_train.append(report['context_use_train']['largest_gap'])
            if figures.split_returns:
                out[(family, method)] = figures
    return out


def mean_sem_cell(values: list[float], digits: int = 0) -> str:
    """Format a table cell: 'mean +- standard error', or '-' for no values."""
    if not values:
        return '-'
    mean, sem = mean_sem(values)
    return f'{mean:.{digits}f} +- {sem:.{digits}f}'


def markdown(rows: list[dict], figures: dict) -> str:
    """Per family: the trainer's final evaluation, then the adaptation report's figures."""
    lines = []
    for family in dict.fromkeys(r['family'] for r in rows):
        lines += [f'## {family}', '', "Trainer's final evaluation (one episode per value):", '',
                  '| method | ' + ' | '.join(SPLIT_ORDER) + ' | seeds | timestep |',
                  '|---' * (len(SPLIT_ORDER) + 3) + '|']
        methods = list(dict.fromkeys(r['method'] for r in rows if r['family'] == family))
        for method in methods:
            cells = {r['split']: r for r in rows
                     if r['family'] == family and r['method'] == method}
            first = next(iter(cells.values()))
            lines.append(f'| {method} | ' + ' | '.join(
                f'{cells[s]["mean"]:.0f} +- {cells[s]["sem"]:.0f}' if s in cells else '-'
                for s in SPLIT_ORDER) + f' | {_seeds_cell(first)} | {first["timestep"]} |')
        lines += ['', *_report_table(family, methods, figures)]
    return '\n'.join(lines)


def _seeds_cell(row: dict) -> str:
    extra = f' (+{row["unfinished"]} unfinished, left out)' if row.get('unfinished') else ''
    return f'{row["seeds"]}{extra}'


def _report_table(family: str, methods: list[str], figures: dict) -> list[str]:
    reported = [m for m in methods if (family, m) in figures]
    if not reported:
        return []
    # Context use at the train values: a column only where some report measured it.
    with_train_gap = any(figures[(family, m)].largest_gap_train for m in reported)
    lines = ['Adaptation report of the final checkpoints '
             '(`zeus_ros.learning_tools.adaptation`):', '',
             '| method | ' + ' | '.join(SPLIT_ORDER) +
             f' | seeds | R^2 decoded (held-out) | live swaps 70 % covered within {SWAP_STEPS}'
             ' steps | largest return gap, context perturbed |'
             + (' the same at the train values |' if with_train_gap else ''),
             '|---' * (len(SPLIT_ORDER) + 5 + with_train_gap) + '|']
    for method in reported:
        fig = figures[(family, method)]
        seeds = max(len(v) for v in fig.split_returns.values())
        train_gap = f' {mean_sem_cell(fig.largest_gap_train)} |' if with_train_gap else ''
        lines.append(f'| {method} | ' + ' | '.join(
            mean_sem_cell(fig.split_returns.get(s, [])) for s in SPLIT_ORDER) +
            f' | {seeds} | {mean_sem_cell(fig.r2, 2)} | {mean_sem_cell(fig.swaps_covered, 2)}'
            f' | {mean_sem_cell(fig.largest_gap)} |'
            + train_gap)
    return [*lines, '',
            *_per_split_table("Mean |speed - target| over each split's targets, m/s "
                              '(lower is better):', 'velocity_error', 3, family, reported,
                              figures),
            *_per_split_table("Success rate over each split's values (the task's own flag at "
                              "an episode's last step):", 'success_rate', 2, family, reported,
                              figures)]


def _per_split_table(title: str, attribute: str, digits: int, family: str,
                     methods: list[str], figures: dict) -> list[str]:
    """Tabulate one figure per split and method, for the methods whose reports have it."""
    having = [m for m in methods if getattr(figures[(family, m)], attribute)]
    if not having:
        return []
    lines = [title, '', '| method | ' + ' | '.join(SPLIT_ORDER) + ' |',
             '|---' * (len(SPLIT_ORDER) + 1) + '|']
    for method in having:
        values = getattr(figures[(family, method)], attribute)
        lines.append(f'| {method} | ' + ' | '.join(
            mean_sem_cell(values.get(s, []), digits) for s in SPLIT_ORDER) + ' |')
    return [*lines, '']


def plot_curves(cfg: SweepConfig, curves: dict) -> list[Path]:
    """Return-vs-steps figures per family (mean over seeds, shaded standard error)."""
    return [plot_groups(family, {m: curves.get((family, m), {}) for m in cfg.methods},
                        cfg.root / f'curves_{family}.png') for family in cfg.families]


def plot_groups(title: str, groups: dict, path: Path) -> Path:
    """One panel per split, one line per group ({label: {seed: Curve}}), as Figure 2."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    # A panel per split some group has (cheetah-run-v1 has no extrapolation split).
    splits = [s for s in SPLIT_ORDER
              if any(mean_curve(runs, s) is not None for runs in groups.values())] or ['train']
    fig, axes = plt.subplots(1, len(splits), figsize=(4.4 * len(splits), 3.6), sharey=True,
                             squeeze=False)
    axes = axes[0]
    for ax, split in zip(axes, splits, strict=True):
        for label, runs in groups.items():
            _plot_method(ax, runs, split, label)
        ax.set_title(f'{title}: {split}')
        ax.set_xlabel('environment steps (thousands)')
        ax.xaxis.set_major_formatter(lambda x, _: f'{x / 1000:g}')
    axes[0].set_ylabel('evaluation return')
    # The legend where the most groups have a line (a family may lack a split).
    max(axes, key=lambda ax: len(ax.get_lines())).legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def mean_curve(runs: dict, split: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
    """Return (env steps, mean, standard error, seeds) over the runs' common steps, or None."""
    usable = [c for c in runs.values() if split in c.returns]
    if not usable:
        return None
    n = min(len(c.env_steps) for c in usable)
    ys = np.asarray([c.returns[split][:n] for c in usable])
    sem = ys.std(0, ddof=1) / np.sqrt(len(ys)) if len(ys) > 1 else np.zeros(n)
    return np.asarray(usable[0].env_steps[:n]), ys.mean(0), sem, len(ys)


def _plot_method(ax: Axes, runs: dict, split: str, method: str) -> None:
    curve = mean_curve(runs, split)
    if curve is None:
        return
    x, mean, sem, seeds = curve
    ax.plot(x, mean, label=f'{method} ({seeds} seed{"s" if seeds > 1 else ""})')
    ax.fill_between(x, mean - sem, mean + sem, alpha=0.2)


def write_results(cfg: SweepConfig, with_report: bool = False) -> str:
    """Write comparison.csv / .md and the curves; return the Markdown."""
    curves = gather(cfg)
    rows = table_rows(curves, lambda family, method, seed: finished(
        run_dir(cfg, family, method, seed), cfg.steps))
    cfg.root.mkdir(parents=True, exist_ok=True)
    with open(cfg.root / 'comparison.csv', 'w', newline='') as f:
        writer = csv.DictWriter(f, ('family', 'method', 'split', 'mean', 'sem', 'seeds',
                                    'timestep', 'unfinished'))
        writer.writeheader()
        writer.writerows(rows)
    figures = adaptation_figures(cfg) if with_report else {}
    text = markdown(rows, figures)
    (cfg.root / 'comparison.md').write_text(text)
    (cfg.root / 'comparison.json').write_text(json.dumps(
        {'rows': rows, 'adaptation': {f'{k[0]}.{k[1]}': asdict(v) for k, v in figures.items()}},
        indent=2))
    plot_curves(cfg, curves)
    return text
