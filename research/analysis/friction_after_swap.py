"""After a swap down from high friction: whether the friction is hidden or misread.

Issue #47: after a segment above the train range the shipped cheetah's
friction estimate stays high (a true 0.57 reads ~0.9 for hundreds of steps),
although its window is only k steps long. Either the windows it sees then
hold no sign of the friction (the gait hides it: feet off the ground, the
body flipped), or they do and the adaptation module misreads them.

For each run and each schedule `0:1.0, 250:H, 500:LOW` (H above, inside or
equal to the train range), this runs the episode in process and, at every
step of the LOW segment, also steps two shadow copies of the state with the
same action, one at the true LOW and one at the value the estimate settles on
elsewhere (`--wrong`): the gap between their next states, over a typical
step's size, says how much one transition could tell the two frictions apart
(near 0: no window could). It reports per schedule, over runs and episodes:
the decoded friction in steps 1-20, 21-100 and 101-250 after the swap down,
the share of steps with the torso pitched beyond 90 degrees (flipped), the
one-step tell-apart gap in the same windows, and the segment's return.

    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/friction_after_swap.py \
        --runs research/results/pilots_36/cw150-rma-raw-k10-swap-s{1,2,3}/checkpoint \
        --episodes 3 --out research/results/friction_after_swap_cw150.md
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
import sys

import numpy as np

from sim_node.env import make_env
from sim_node.families import as_values
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import EpisodeProbe, run_episode

SEGMENT = 250            # steps per schedule segment
WINDOWS = ((0, 20), (20, 100), (100, 250))   # steps after the swap down
PITCH_QPOS = 2           # cheetah's qpos: rootx, rootz, rooty (the torso's pitch), joints


class TellApartProbe(EpisodeProbe):
    """At every step from `start`: the next state under the true and a wrong friction."""

    def __init__(self, family: str, start: int, wrong: float):
        self.start, self.wrong, self.step = start, wrong, 0
        self.shadow = make_env(family, as_values(wrong), seed=0)
        self.gaps: list[float] = []
        self.sizes: list[float] = []
        self.pitch: list[float] = []

    def before_step(self, env, action: np.ndarray) -> None:
        self.pitch.append(float(env.physics.data.qpos[PITCH_QPOS]))
        if self.step >= self.start:
            before = env.observation()
            nxt = []
            for value in (env.param_values, as_values(self.wrong)):
                self.shadow.set_values(value)
                self.shadow.copy_state_from(env)
                nxt.append(self.shadow.step(action).observation)
            self.gaps.append(float(np.linalg.norm(nxt[0] - nxt[1])))
            self.sizes.append(float(np.linalg.norm(nxt[0] - before)))
        self.step += 1


@dataclass(frozen=True)
class SegmentFigures:
    """One episode's LOW segment, after the swap down."""

    decoded: tuple[float, ...]     # mean decoded friction per window of WINDOWS
    tell_apart: tuple[float, ...]  # mean one-step gap / mean step size per window
    flipped: float                 # share of steps with the torso beyond 90 degrees of pitch
    segment_return: float


def segment_figures(model: InferenceModel, high: float, low: float, wrong: float,
                    seed: int) -> SegmentFigures:
    start = 2 * SEGMENT
    probe = TellApartProbe(model.family, start, wrong)
    rec = run_episode(model, model.family, 1.0, seed,
                      swap_schedule={SEGMENT: high, start: low}, max_steps=3 * SEGMENT,
                      probe=probe)
    est = np.asarray(rec.estimates, dtype=float).reshape(len(rec.rewards), -1)[start:, 0]
    gaps, sizes = np.asarray(probe.gaps), np.asarray(probe.sizes)
    pitch = np.asarray(probe.pitch[start:])   # a hinge: a full turn is upright again
    return SegmentFigures(
        tuple(float(est[a:b].mean()) for a, b in WINDOWS),
        tuple(float(gaps[a:b].mean() / sizes[a:b].mean()) for a, b in WINDOWS),
        float(np.mean(np.cos(pitch) < 0.0)), float(np.sum(rec.rewards[start:])))


def row(label: str, figures: list[SegmentFigures]) -> str:
    def cell(values: list[float], digits: int) -> str:
        error = np.std(values) / np.sqrt(len(values))
        return f'{np.mean(values):.{digits}f} +- {error:.{digits}f}'
    decoded = [cell([f.decoded[i] for f in figures], 2) for i in range(len(WINDOWS))]
    tell = [cell([f.tell_apart[i] for f in figures], 3) for i in range(len(WINDOWS))]
    return (f'| {label} | {len(figures)} | ' + ' | '.join(decoded) + ' | ' + ' | '.join(tell)
            + f' | {cell([f.flipped for f in figures], 2)} | '
            f'{cell([f.segment_return for f in figures], 0)} |')


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', nargs='+', type=Path, required=True, help='checkpoint folders')
    parser.add_argument('--highs', nargs='+', type=float, default=[6.0, 2.5, 1.0],
                        help='frictions of the middle segment (1.0: no high segment)')
    parser.add_argument('--low', type=float, default=0.57, help='friction after the swap down')
    parser.add_argument('--wrong', type=float, default=0.91,
                        help='the value compared with the true one (the misread seen in #47)')
    parser.add_argument('--episodes', type=int, default=3, help='episode seeds per run')
    parser.add_argument('--out', type=Path, help='write the table here')
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    models = [InferenceModel.load(p) for p in args.runs]
    heads = [f'decoded, steps {a + 1}-{b}' for a, b in WINDOWS] \
        + [f'tell-apart, steps {a + 1}-{b}' for a, b in WINDOWS]
    lines = [f'| 1.0 -> H -> {args.low:g} | episodes | ' + ' | '.join(heads)
             + ' | flipped | segment return |', '|---|---|' + '---|' * (len(heads) + 2)]
    for high in args.highs:
        figures = [segment_figures(m, high, args.low, args.wrong, seed)
                   for m in models for seed in range(args.episodes)]
        lines.append(row(f'H = {high:g}', figures))
        print(lines[-1], flush=True)
    text = '\n'.join(lines)
    command = 'PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/friction_after_swap.py ' \
        + ' '.join(map(str, sys.argv[1:] if argv is None else argv))
    print(text)
    if args.out:
        args.out.write_text(f'`{command}`\n\n{text}\n\nTell-apart: the norm of the gap between '
                            f'the next observations under {args.low:g} and {args.wrong:g} '
                            'from the same state and action, over the norm of a step '
                            "(mean over the window's steps). Runs: "
                            + ', '.join(f'`{p}`' for p in args.runs) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
