"""Why reacher-length's estimate compresses: a window of an arm at rest holds |L - L_told| only.

The policy puts the fingertip where it would be for the length it believes,
L_told. With the true forearm L the tip sits (L - L_told) along the forearm
from the target, so the reward measures |L - L_told|, the same for a forearm
that is too long and one that is too short, and with the arm at rest the
joint state does not move. A window of the last k transitions taken at rest
then holds no sign: the length it reads can only be told apart from its
mirror image while the arm moves (reaching, or just after a swap). This
measures it: the policy is given its latent for ``--told`` (the oracle's
true-parameter input, or `rma`'s teacher latent; estimate_gap.py's probe)
at true lengths placed symmetrically around it, and the reward and the
joint-state change are averaged after the arm has settled.

    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/length_sign_ambiguity.py \
        --weights weights/reacher-length-rma-k10-swaps

Writes research/results/<name>.md.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
import sys

import numpy as np

from estimate_gap import truth_probe   # its folder is on the path when the script runs
from summarize_runs import mean_se
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode

RESULTS = Path(__file__).resolve().parents[1] / 'results'


@dataclass(frozen=True)
class AtLength:
    """Means over episodes at one true length, the policy told another."""

    true: float
    reward_moving: str     # 'mean +- s.e.' over episodes of the per-step reward before settling
    reward_settled: str    # the same after settling
    state_change: float                   # mean |s' - s| per step after settling


def at_length(model: InferenceModel, true: float, told: float, episodes: int,
              settle: int) -> AtLength:
    moving, settled, change = [], [], []
    for seed in range(episodes):
        rec = run_episode(model, model.family, true, seed, probe=truth_probe(model, told))
        moving.append(float(rec.rewards[:settle].mean()))
        settled.append(float(rec.rewards[settle:].mean()))
        change.append(float(np.abs(np.diff(rec.observations[settle:], axis=0)).mean()))
    return AtLength(true, mean_se(moving, 3), mean_se(settled, 3), float(np.mean(change)))


def render(rows: list[AtLength], args: argparse.Namespace, argv: list[str]) -> str:
    lines = [f'# Told {args.told:g}, true lengths around it: reward and motion once the arm '
             'has reached',
             '', '`PYTHONPATH=. OMP_NUM_THREADS=1 python '
             f'research/analysis/length_sign_ambiguity.py {" ".join(argv)}`: the policy of '
             f'`{args.weights}` given its latent for '
             f'{args.told:g} at every true length, {args.episodes} episodes each (start seeds '
             f'0-{args.episodes - 1}); "settled" is steps {args.settle}-1000.', '',
             '| true length | L - told | reward, steps 0-' f'{args.settle} | reward, settled | '
             'mean abs. joint-state change per step, settled |', '|---|---|---|---|---|']
    for row in rows:
        lines.append(f'| {row.true:g} | {row.true - args.told:+.3f} | '
                     f'{row.reward_moving} | {row.reward_settled} | '
                     f'{row.state_change:.2e} |')
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--weights', required=True, help='a reacher-length run or checkpoint '
                        '(oracle, or rma: its weights carry the teacher)')
    parser.add_argument('--told', type=float, default=0.15, help='the length the policy is told')
    parser.add_argument('--offsets', type=float, nargs='+', default=[0.0, 0.03, 0.06],
                        help='true lengths at told -/+ each offset')
    parser.add_argument('--episodes', type=int, default=5, help='episodes per true length')
    parser.add_argument('--settle', type=int, default=300, help='steps before the arm is at rest')
    parser.add_argument('--name', default='length_sign_ambiguity', help='results file stem')
    args = parser.parse_args(argv)
    model = InferenceModel.load(args.weights)
    trues = sorted({round(args.told + sign * off, 4) for off in args.offsets for sign in (-1, 1)})
    rows = []
    for true in trues:
        rows.append(at_length(model, true, args.told, args.episodes, args.settle))
        print(rows[-1], flush=True)
    (RESULTS / f'{args.name}.md').write_text(render(rows, args, argv))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
