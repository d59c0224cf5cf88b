"""Random live schedules: return, estimate error and lag after each swap, per method (#47).

A schedule chosen by hand can flatter a method (issue #47: the shipped
friction pair leads on 1.0 -> 4.0 -> 0.06 and trails on another). Here every
episode draws its own schedule from the family's live range, runs the demo's
episode in process (`evaluate.run_episode`, which the ROS episode equals,
test_parity) for every run folder given, and measures:

- the episode return, per method the mean over its runs of each run's mean
  over episodes (+- the standard error over runs), and the share of the
  sac-oracle gap, (method - sac) / (oracle - sac), from the groups whose
  method is `sac` and `oracle` (n/a unless exactly one of each is given);
- the estimate's error in log space, |ln(estimate / true)|, per segment:
  over all its steps and over its steps after the first SETTLE (once a window
  could have caught up); a run's figure is the mean over its segments (each
  segment weighs the same), and R^2 of ln(estimate) against ln(true) is taken
  over every step with a full window (the adaptation report's steps) of a
  run's episodes. An estimate <= 0 (a linear decoder can give one) has no
  logarithm: it counts as a tenth of the live range's lower end;
- per swap: its direction (up, down), the region of the new value (below the
  train span; low, mid, high: thirds of the train span in log space; above
  it) and the lag, steps from the swap until the estimate is within 20 % of
  the true value in log space and stays there 5 steps
  (`adaptation.steps_to_within`, the adaptation report's lag). A swap whose
  segment ends first is censored: counted as such, never averaged as a
  number; its median sorts it after every measured lag ('never' when half or
  more are censored);
- the mean reward per step in the segments at each region's values (where
  a method gains or loses against the references);
- issue #47 item 3's target: the share of swaps inside the train range (both
  values in the train span) whose estimate covers 70 % of the change in log
  space within 20 steps. This is the adaptation report's "swaps within 20
  steps" count (`adaptation.steps_to_cover`: from the estimate's mean over the
  50 steps before the swap, first step at 70 % of the true change) taken on
  ln(estimate) and ln(value) instead of the values themselves.

Schedules (`draw_schedule`): SWAPS_MIN-SWAPS_MAX swaps at random steps with
every segment at least MIN_SEGMENT steps long, values log-uniform over the
live range with consecutive values at least MIN_RATIO apart. Episode seed e
runs draw e (numpy's default_rng(e)), so every run sees the same schedules.

    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/random_schedules.py \
        --runs research/results/pilots_36/cw150-{oracle,sac,rma-raw-k10-swap}-s{1,2,3}/checkpoint \
        --episodes 10 --out research/results/random_schedules_47/cw150.md

writes the tables to FILE.md (first line: the command) and the per-run
figures to FILE.json, from which other tables can be recomputed.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from dataclasses import asdict, dataclass
import json
import math
from pathlib import Path
import sys
from typing import Iterable

import numpy as np

from live_swaps import run_label   # its folder is on the path when the script runs
from summarize_runs import mean_se
from sim_node.families import get_sim_family
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.adaptation import r_squared, steps_to_cover, steps_to_within
from zeus_ros.learning_tools.evaluate import EpisodeRecord, run_episode

SWAPS_MIN, SWAPS_MAX = 3, 5   # swaps per episode (1000 steps: a segment of 170-250 steps)
MIN_SEGMENT = 60              # steps: a lag of tens of steps and the settled error fit in it
MIN_RATIO = 1.5               # consecutive values: a swap, not a nudge (> the 20 % band)
SETTLE = 20                   # the item-3 horizon; the settled error starts after it
REGIONS = ('below train', 'low', 'mid', 'high', 'above train')
DIRECTIONS = ('up', 'down')


@dataclass(frozen=True)
class SegmentFigures:
    """One stretch of an episode at one true value."""

    start: int
    steps: int
    value: float
    region: str
    direction: str          # of the swap that began it; 'start' for the episode's first
    reward: float           # mean reward per step over it
    error_all: float        # mean |ln(estimate / true)| over its steps (NaN: no estimate)
    error_settled: float    # the same after its first SETTLE steps


@dataclass(frozen=True)
class SwapFigures:
    """How the estimate followed one swap."""

    step: int
    from_value: float
    to_value: float
    direction: str
    region: str
    inside_train: bool      # both values inside the train span
    lag: int | None         # None: censored (not within 20 % for 5 steps before the segment ends)
    covered_70_in_20: bool  # 70 % of the change in log space within SETTLE steps


@dataclass(frozen=True)
class RunResult:
    """One run's figures over its episodes."""

    run: str
    label: str
    method: str
    returns: tuple[float, ...]          # by episode seed
    r2_log: float | None                # None: no estimate (sac)
    r2_log_train: float | None          # the same over the steps inside the train span
    segments: tuple[SegmentFigures, ...]
    swaps: tuple[SwapFigures, ...]


# -- schedules and regions ---------------------------------------------------------
def draw_schedule(live_range: tuple[float, float], steps: int, seed: int,
                  swaps: tuple[int, int] = (SWAPS_MIN, SWAPS_MAX), min_segment: int = MIN_SEGMENT,
                  min_ratio: float = MIN_RATIO) -> dict[int, float]:
    """Return {step: value} from step 0 (run_episode's step indexes), drawn from `seed` alone.

    The swap count is uniform over `swaps` (both ends included); the swap
    steps are uniform over the placements leaving every segment `min_segment`
    steps or more; values are log-uniform over `live_range`, each at least
    `min_ratio` times above or below the one before.
    """
    low, high = live_range
    if not 0 < low < high / min_ratio:
        raise ValueError(f'no two values {min_ratio}x apart in the live range {live_range}')
    if (swaps[1] + 1) * min_segment > steps:
        raise ValueError(f'{swaps[1]} swaps leave a segment under {min_segment} of {steps} steps')
    rng = np.random.default_rng(seed)
    count = int(rng.integers(swaps[0], swaps[1] + 1))
    # Segments of min_segment each, plus the slack split at count sorted points.
    slack = np.sort(rng.integers(0, steps - (count + 1) * min_segment + 1, size=count))
    starts = [0, *(int(s) + (i + 1) * min_segment for i, s in enumerate(slack))]
    values = [_log_uniform(rng, low, high)]
    while len(values) < len(starts):
        value = _log_uniform(rng, low, high)
        if abs(math.log(value / values[-1])) >= math.log(min_ratio):   # else redraw
            values.append(value)
    return dict(zip(starts, values, strict=True))


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def region(value: float, train_span: tuple[float, float]) -> str:
    """Name where a value lies: below or above the train span, or its low / mid / high third.

    Thirds in log space; the span's ends (train values) are inside it, and a
    value on the boundary of two thirds belongs to the upper one.
    """
    low, high = train_span
    if value < low:
        return 'below train'
    if value > high:
        return 'above train'
    third = (math.log(value) - math.log(low)) / (math.log(high) - math.log(low)) * 3
    return REGIONS[1 + min(int(third), 2)]


def gap_share(method: float, sac: float | None, oracle: float | None) -> float | None:
    """Share of the sac-oracle gap a return closes: 0 at sac, 1 at the oracle (None: no gap)."""
    if sac is None or oracle is None or oracle == sac:
        return None
    if method == sac:   # exactly 0, not the -0 % a negative gap would print
        return 0.0
    return (method - sac) / (oracle - sac)


# -- one episode's measures --------------------------------------------------------
def log_errors(estimates: np.ndarray, truth: np.ndarray, floor: float) -> np.ndarray:
    """|ln(estimate / true)| per step; an estimate under `floor` (or <= 0) counts as `floor`."""
    return np.abs(np.log(np.maximum(estimates, floor)) - np.log(truth))


def segment_figures(rewards: np.ndarray, errors: np.ndarray, start: int, end: int,
                    value: float, direction: str,
                    train_span: tuple[float, float]) -> SegmentFigures:
    """Reward and error over one segment's steps [start, end), the error also after SETTLE."""
    settled = errors[start + SETTLE:end]
    return SegmentFigures(start, end - start, value, region(value, train_span), direction,
                          float(rewards[start:end].mean()), float(errors[start:end].mean()),
                          float(settled.mean()) if settled.size else math.nan)


def swap_figures(estimates: np.ndarray, floor: float, start: int, end: int, before: float,
                 after: float, train_span: tuple[float, float]) -> SwapFigures:
    """Direction, region, lag and item 3's coverage of the swap at `start` (segment to `end`)."""
    lag = steps_to_within(estimates[:end], start, after)
    # The adaptation report's coverage, on logarithms (its pre-swap mean is
    # inside the segment before: segments are at least MIN_SEGMENT > 50 steps).
    logs = np.log(np.maximum(estimates[:end], floor))
    covered = steps_to_cover(logs, start, math.log(before), math.log(after))
    inside = all(train_span[0] <= v <= train_span[1] for v in (before, after))
    return SwapFigures(start, before, after, 'up' if after > before else 'down',
                       region(after, train_span), inside, lag,
                       covered is not None and covered <= SETTLE)


def episode_figures(rec: EpisodeRecord, schedule: dict[int, float], floor: float,
                    train_span: tuple[float, float]) -> tuple[list, list]:
    """Segments of one episode (cut short if it ended early) and, with an estimate, swaps."""
    estimates = np.asarray(rec.estimates, float).reshape(len(rec.rewards))
    measured = not np.all(np.isnan(estimates))   # sac, or a latent with no decoder: no estimate
    errors = (log_errors(estimates, np.asarray(rec.param_values, float), floor) if measured
              else np.full(len(estimates), math.nan))
    starts = [s for s in schedule if s < len(estimates)]
    ends = [*starts[1:], len(estimates)]
    segments, swaps = [], []
    for i, (start, end) in enumerate(zip(starts, ends, strict=True)):
        value = schedule[start]
        direction = 'start' if i == 0 else ('up' if value > schedule[starts[i - 1]] else 'down')
        segments.append(segment_figures(np.asarray(rec.rewards, float), errors, start, end,
                                        value, direction, train_span))
        if i and measured:
            swaps.append(swap_figures(estimates, floor, start, end, schedule[starts[i - 1]],
                                      value, train_span))
    return segments, swaps


def run_result(path: Path, episodes: int, seed: int, steps: int,
               swaps: tuple[int, int], min_segment: int) -> RunResult:
    """Run one checkpoint over `episodes` drawn schedules (episode seed e: draw e)."""
    model = InferenceModel.load(path)
    spec = get_sim_family(model.family)
    if len(spec.live_params) != 1:
        raise SystemExit(f'{model.family}: one live parameter only')
    live = spec.live_params[0].live_range
    train_span = (min(spec.train), max(spec.train))
    floor = live[0] / 10   # an estimate <= 0 has no log: counted as far below the range
    returns, segments, swap_list, truth, estimate = [], [], [], [], []
    for e in range(seed, seed + episodes):
        schedule = draw_schedule(live, steps, e, swaps, min_segment)
        rec = run_episode(model, model.family, schedule[0], e, max_steps=steps,
                          swap_schedule={s: v for s, v in schedule.items() if s})
        returns.append(float(rec.episode_return))
        seg, sw = episode_figures(rec, schedule, floor, train_span)
        segments += seg
        swap_list += sw
        if np.all(np.isnan(rec.estimates)):
            continue
        truth.append(np.log(np.asarray(rec.param_values, float)[model.k:]))
        estimate.append(np.log(np.maximum(np.asarray(rec.estimates, float)[model.k:], floor)))
    r2 = r2_train = None
    if truth:
        truth, estimate = np.concatenate(truth), np.concatenate(estimate)
        r2 = r_squared(truth, estimate)
        # Beyond the train span an estimate may saturate at its edge by design (#36): the
        # in-span figure says how well the values training spans are read.
        inside = (truth >= np.log(train_span[0])) & (truth <= np.log(train_span[1]))
        r2_train = r_squared(truth[inside], estimate[inside])
    return RunResult(str(path), run_label(model), model.method_name, tuple(returns), r2,
                     r2_train, tuple(segments), tuple(swap_list))


# -- tables ------------------------------------------------------------------------
def groups_of(results: Iterable[RunResult]) -> dict[str, list[RunResult]]:
    """Group the runs by label, labels sorted."""
    groups: dict[str, list[RunResult]] = defaultdict(list)
    for r in results:
        groups[r.label].append(r)
    return dict(sorted(groups.items()))


def reference_return(groups: dict[str, list[RunResult]], method: str) -> float | None:
    """Mean return of the one group of `method` (None if there is none, or several)."""
    found = [runs for runs in groups.values() if runs[0].method == method]
    if len(found) != 1:
        return None
    return float(np.mean([np.mean(r.returns) for r in found[0]]))


def _run_mean(values: list[float]) -> float | None:
    """Mean of one run's measured values (NaN: not measured); None if none."""
    kept = [v for v in values if not math.isnan(v)]
    return float(np.mean(kept)) if kept else None


def returns_table(results: list[RunResult]) -> str:
    """Markdown: return, share of the sac-oracle gap, R^2 and error in log space per method."""
    groups = groups_of(results)
    sac, oracle = reference_return(groups, 'sac'), reference_return(groups, 'oracle')
    lines = ['| method | runs | return | share of the sac-oracle gap | R^2, ln estimate '
             '| R^2 inside the train span | \\|ln(estimate/true)\\|, all steps '
             '| the same after 20 steps |',
             '|---|---|---|---|---|---|---|---|']
    for label, runs in groups.items():
        means = [float(np.mean(r.returns)) for r in runs]
        share = gap_share(float(np.mean(means)), sac, oracle)
        error = [_run_mean([s.error_all for s in r.segments]) for r in runs]
        settled = [_run_mean([s.error_settled for s in r.segments]) for r in runs]
        lines.append(f'| {label} | {len(runs)} | {mean_se(means, 1)} | '
                     + ('n/a' if share is None else f'{share:.0%}') + ' | '
                     + f'{mean_se([r.r2_log for r in runs], 2)} | '
                     + f'{mean_se([r.r2_log_train for r in runs], 2)} | {mean_se(error, 2)} | '
                     + f'{mean_se(settled, 2)} |')
    if sac is not None and oracle is not None:   # a share of a negative gap reads backwards
        lines.append(f'\nThe sac-oracle gap: {oracle - sac:+.1f} (oracle {oracle:.1f}, '
                     f'sac {sac:.1f}).')
    return '\n'.join(lines)


def median_lag(lags: list[int | None]) -> str:
    """Median lag with censored swaps sorted after every measured one ('never' if they hold it)."""
    if not lags:
        return '-'
    ordered = sorted(lags, key=lambda lag: math.inf if lag is None else lag)
    middle = (len(ordered) - 1) / 2
    low, high = ordered[math.floor(middle)], ordered[math.ceil(middle)]
    if low is None or high is None:
        return 'never'
    return f'{(low + high) / 2:g}'


def lag_table(results: list[RunResult]) -> str:
    """Markdown: per method, swap direction and region of the new value: lag and error."""
    lines = ['| method | direction | region | swaps | median lag (steps) | censored '
             '| 70 % in 20 steps | \\|ln(estimate/true)\\| after 20 steps |',
             '|---|---|---|---|---|---|---|---|']
    for label, runs in groups_of(results).items():
        if all(r.r2_log is None for r in runs):
            continue   # no estimate
        for direction in DIRECTIONS:
            for where in REGIONS:
                swaps = [s for r in runs for s in r.swaps
                         if (s.direction, s.region) == (direction, where)]
                if not swaps:
                    continue
                lags = [s.lag for s in swaps]
                censored = sum(lag is None for lag in lags) / len(lags)
                covered = sum(s.covered_70_in_20 for s in swaps) / len(swaps)
                error = [_run_mean([s.error_settled for s in r.segments
                                    if (s.direction, s.region) == (direction, where)])
                         for r in runs]
                lines.append(f'| {label} | {direction} | {where} | {len(swaps)} | '
                             f'{median_lag(lags)} | {censored:.0%} | {covered:.0%} | '
                             f'{mean_se(error, 2)} |')
    return '\n'.join(lines)


def region_reward_table(results: list[RunResult]) -> str:
    """Markdown: mean reward per step in the segments at each region's values, per method."""
    lines = ['| method | ' + ' | '.join(REGIONS) + ' |', '|---|' + '---|' * len(REGIONS)]
    for label, runs in groups_of(results).items():
        cells = [mean_se([_run_mean([s.reward for s in r.segments if s.region == where])
                          for r in runs], 3) for where in REGIONS]
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def coverage_table(results: list[RunResult]) -> str:
    """Markdown: item 3's target, swaps inside the train range covered 70 % within 20 steps."""
    lines = ['| method | up: covered / swaps | share | down: covered / swaps | share |',
             '|---|---|---|---|---|']
    for label, runs in groups_of(results).items():
        if all(r.r2_log is None for r in runs):
            continue
        cells = []
        for direction in DIRECTIONS:
            swaps = [s for r in runs for s in r.swaps
                     if s.inside_train and s.direction == direction]
            covered = sum(s.covered_70_in_20 for s in swaps)
            cells += [f'{covered} / {len(swaps)}',
                      f'{covered / len(swaps):.0%}' if swaps else '-']
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


# -- the program ---------------------------------------------------------------------
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', nargs='+', type=Path, required=True,
                        help='checkpoint folders (metadata.json and model.safetensors)')
    parser.add_argument('--episodes', type=int, default=10, help='episode seeds (and draws)')
    parser.add_argument('--seed', type=int, default=0, help='first episode seed')
    parser.add_argument('--steps', type=int, default=1000, help='steps per episode')
    parser.add_argument('--swaps-min', type=int, default=SWAPS_MIN, help='fewest swaps')
    parser.add_argument('--swaps-max', type=int, default=SWAPS_MAX, help='most swaps')
    parser.add_argument('--min-segment', type=int, default=MIN_SEGMENT,
                        help='shortest segment, steps')
    parser.add_argument('--out', type=Path, help='write the tables here (and FILE.json)')
    return parser.parse_args(argv)


def report(results: list[RunResult], args: argparse.Namespace) -> str:
    """Return the three tables, with what they measure."""
    return (f'Random schedules: {args.swaps_min}-{args.swaps_max} swaps per '
            f'{args.steps}-step episode (segments >= {args.min_segment} steps, values '
            f'log-uniform over the live range, >= {MIN_RATIO}x apart), episode seeds '
            f'{args.seed}-{args.seed + args.episodes - 1} (seed e: draw e); mean +- standard '
            'error over runs.\n\n'
            f'{returns_table(results)}\n\n'
            'Per swap, by direction and region of the new value (lag: steps until within '
            '20 % of the true value in log space for 5 steps; censored: not within before '
            "the segment ended; all runs' swaps pooled, every run running the same "
            'draws):\n\n'
            f'{lag_table(results)}\n\n'
            'Mean reward per step over the segments at values in each region (every '
            "segment, the first included; a run's mean over its segments):\n\n"
            f'{region_reward_table(results)}\n\n'
            'Swaps with both values inside the train range, 70 % of the change (log space) '
            'covered within 20 steps (issue #47 item 3):\n\n'
            f'{coverage_table(results)}\n')


def json_ready(value: object) -> object:
    """Return `value` with NaN as None (JSON has none) and floats to 6 significant digits."""
    if isinstance(value, float):
        return None if math.isnan(value) else float(f'{value:.6g}')
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(v) for v in value]
    return value


def write_out(out: Path, text: str, results: list[RunResult], argv: list[str]) -> None:
    """FILE.md (first line: the command) and FILE.json with every run's figures."""
    out.parent.mkdir(parents=True, exist_ok=True)
    command = ' '.join(['PYTHONPATH=. OMP_NUM_THREADS=1 python',
                        'research/analysis/random_schedules.py', *argv])
    listing = '\n'.join(f'- `{r.run}` ({r.label}): by episode seed '
                         + ', '.join(f'{x:.0f}' for x in r.returns) for r in results)
    out.write_text(f'`{command}`\n\n{text}\nEpisode returns per run:\n\n{listing}\n')
    figures = json_ready([asdict(r) for r in results])   # NaN: not measured (no estimate)
    out.with_suffix('.json').write_text(json.dumps(   # compact: a few hundred swaps per run
        {'command': command, 'runs': figures}, separators=(',', ':'), allow_nan=False) + '\n')


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    results = []
    for path in args.runs:
        results.append(run_result(path, args.episodes, args.seed, args.steps,
                                  (args.swaps_min, args.swaps_max), args.min_segment))
        r = results[-1]
        print(f'{path}: {r.label} return {np.mean(r.returns):.1f}'
              + ('' if r.r2_log is None else f', R^2 (log) {r.r2_log:.2f}'), flush=True)
    text = report(results, args)
    print(text)
    if args.out:
        write_out(args.out, text, results, argv)
    return 0


if __name__ == '__main__':
    sys.exit(main())
