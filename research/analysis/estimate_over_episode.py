"""When in an episode a context method reads its parameter: while the robot moves, or at rest.

A length estimate that stops short beyond the train range can fall short
for two reasons: the regressor never extrapolates (the estimate is short
from the first steps, while the arm still moves), or the windows stop
showing the length once the arm rests (the estimate is right while it moves
and drifts back at rest; `length_sign_ambiguity.py`). This tells them apart:
per true value, the mean decoded estimate and the mean joint-state change
per step in windows of the episode (steps [0, 10), [10, 30), ...).

    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/estimate_over_episode.py \
        --weights weights/reacher-length-rma-k10-swaps --values 0.06 0.09 0.15 0.17 0.19 0.21

Writes research/results/<name>.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys

import numpy as np

from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode

RESULTS = Path(__file__).resolve().parents[1] / 'results'
EDGES = (0, 10, 30, 100, 300, 1000)   # step windows: reaching first, then at rest
SPANS = tuple(zip(EDGES[:-1], EDGES[1:], strict=True))


def window_means(values: np.ndarray) -> list[float]:
    """Mean of a per-step series over each window of SPANS it reaches."""
    return [float(np.mean(values[a:b])) for a, b in SPANS if a < len(values)]


def measure(model: InferenceModel, value: float,
            episodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Per window: mean estimate and mean joint-state change per step, over episodes."""
    estimates, motion = [], []
    for seed in range(episodes):
        record = run_episode(model, model.family, value, seed)
        estimates.append(window_means(np.asarray(record.estimates, dtype=float).reshape(-1)))
        moved = np.abs(np.diff(record.observations, axis=0)).mean(axis=1)
        # Step 0 has no step before it: it counts as moving like step 1, so windows align.
        motion.append(window_means(np.concatenate([[moved[0]], moved])))
    return np.mean(estimates, axis=0), np.mean(motion, axis=0)


def table(rows: list[tuple[float, np.ndarray, np.ndarray]]) -> list[str]:
    spans = [f'{a}-{b}' for a, b in SPANS]
    lines = ['| true value | ' + ' | '.join(f'estimate, steps {s}' for s in spans)
             + ' | ' + ' | '.join(f'joint-state change per step, {s}' for s in spans) + ' |',
             '|---' * (1 + 2 * len(spans)) + '|']
    for value, est, moved in rows:
        lines.append(f'| {value:g} | ' + ' | '.join(f'{e:.3f}' for e in est) + ' | '
                     + ' | '.join(f'{m:.1e}' for m in moved) + ' |')
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--weights', required=True, help='a run or weights directory')
    parser.add_argument('--values', type=float, nargs='+', required=True, help='true values')
    parser.add_argument('--episodes', type=int, default=2, help='deterministic episodes a value')
    parser.add_argument('--name', default='estimate_over_episode', help='results file name')
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    model = InferenceModel.load(args.weights)
    rows = [(v, *measure(model, v, args.episodes)) for v in args.values]
    command = ('PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/estimate_over_episode.py '
               + ' '.join(argv))
    text = [f'# When {model.family} reads its parameter: `{args.weights}`', '',
            f'`{command}`; {args.episodes} deterministic episodes a value (seeds 0..'
            f'{args.episodes - 1}), the mean decoded estimate and the mean absolute change of '
            'the observation per step, by window of steps.', '', *table(rows), '']
    (RESULTS / f'{args.name}.md').write_text('\n'.join(text))
    print('\n'.join(text))
    return 0


if __name__ == '__main__':
    sys.exit(main())
