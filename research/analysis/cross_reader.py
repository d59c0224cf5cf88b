"""Is it the reader or the windows? Every context reader on every policy's windows.

On cheetah-run-v0 the `up-osi` baseline reads the held-out torso lengths at
R^2 0.96 and this project's `zeus-id` at 0.85 (both three seeds, their own
policies). The two differ in the reader (OSI: k = 5, its output the
normalised length; zeus-id: k = 25, a 16-d latent shaped by model and
metric losses, read by a decoder) AND in the data it reads (each policy
acts on its own estimate, so it runs its own gait). This crosses them:
each ACTOR checkpoint runs deterministic episodes at the held-out lengths,
acting on its own context as deployed, and every READER checkpoint decodes
the length from the same transitions, its own k at a time. A reader that
is good on every actor's windows is a good reader; an actor whose windows
every reader reads well runs an informative gait.

R^2 is over every step with a full window of that reader (as the adaptation
report's), pooled over the held-out values, episode seeds 0-1.

    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/cross_reader.py \
        --actors research/results/cheetah_v0_50k/cv0-{up-osi,zeus-id}-s{1,2,3} \
        --readers research/results/cheetah_v0_50k/cv0-{up-osi,zeus-id,cadm}-s{1,2,3}

Writes research/results/cross_reader.{md,csv} (``--name`` to change the stem).
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sim_node.families import get_family
from zeus_ros.learning_tools.adaptation import HELD_OUT, r_squared
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode

RESULTS = Path(__file__).resolve().parents[1] / 'results'


@dataclass(frozen=True)
class Transitions:
    """Window rows (s, a, r, s') of one episode, in ContextWindow's layout, and the truth."""

    rows: np.ndarray    # [T, row_dim] float32
    value: float


@dataclass(frozen=True)
class CrossResult:
    actor: str
    actor_method: str
    reader: str
    reader_method: str
    reader_k: int
    r2: float
    steps: int


def episode_rows(record) -> np.ndarray:
    """(s_t, a_t, r_t, s_t+1) for every step whose next state was recorded."""
    obs, act, rew = record.observations, record.actions, record.rewards
    t = len(obs) - 1
    return np.concatenate([obs[:t], act[:t], rew[:t, None], obs[1:t + 1]],
                          axis=1).astype(np.float32)


def actor_transitions(actor: InferenceModel, values, episodes: int) -> list[Transitions]:
    """Run the actor's own deterministic episodes at each value (seeds 0 .. episodes - 1)."""
    return [Transitions(episode_rows(run_episode(actor, actor.family, v, seed)), float(v))
            for v in values for seed in range(episodes)]


def reader_estimates(reader: InferenceModel, rows: np.ndarray) -> np.ndarray:
    """Return the reader's decoded value after every full window of its k rows."""
    k = reader.k
    windows = np.lib.stride_tricks.sliding_window_view(rows, (k, rows.shape[1]))[:, 0]
    mask = torch.ones(windows.shape[:2], dtype=torch.bool)
    with torch.no_grad():
        latent = reader.method.deployed_context(torch.from_numpy(windows.copy()), mask, None)
        normalised = reader.method.decode(latent)[:, 0].numpy().astype(np.float64)
    return normalised * reader.param_scale[0] + reader.param_offset[0]


def cross(actor_name: str, actor: InferenceModel, data: list[Transitions],
          readers: dict) -> list[CrossResult]:
    """R^2 of every reader on one actor's transitions."""
    out = []
    for name, reader in readers.items():
        truth, estimate = [], []
        for episode in data:
            if len(episode.rows) < reader.k:
                continue
            est = reader_estimates(reader, episode.rows)
            estimate.append(est)
            truth.append(np.full(len(est), episode.value))
        truth, estimate = np.concatenate(truth), np.concatenate(estimate)
        out.append(CrossResult(actor_name, actor.method_name, name,
                               reader.method_name, reader.k,
                               r_squared(truth, estimate), len(truth)))
    return out


def summary(results: list[CrossResult]) -> list[tuple]:
    """(reader method, actor method, mean R^2, standard error over readers, pairs)."""
    rows = []
    for rm in dict.fromkeys(r.reader_method for r in results):
        for am in dict.fromkeys(r.actor_method for r in results):
            by_reader = {}
            for r in results:
                if r.reader_method == rm and r.actor_method == am:
                    by_reader.setdefault(r.reader, []).append(r.r2)
            means = np.array([np.mean(v) for v in by_reader.values()])
            sem = means.std(ddof=1) / np.sqrt(len(means)) if len(means) > 1 else 0.0
            rows.append((rm, am, float(means.mean()), float(sem),
                         sum(len(v) for v in by_reader.values())))
    return rows


def write(stem: Path, results: list[CrossResult], family: str, values, episodes: int,
          command: str) -> None:
    with open(stem.with_suffix('.csv'), 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(CrossResult.__dataclass_fields__)
        w.writerows([list(vars(r).values()) for r in results])
    lines = [f'# Readers x actors: decoded {family} parameter, R^2 on held-out values', '',
             f'`{command}`', '',
             f'Held-out values {list(values)}, {episodes} deterministic episodes each, every '
             "step with a full window of the reader's k. Rows: the reader's method; columns: "
             "whose policy ran the episodes. Mean +- standard error over the reader's seeds "
             '(each reader seed averaged over the actor seeds first).', '',
             '| reader \\ actor | ' + ' | '.join(dict.fromkeys(r.actor_method for r in results))
             + ' |', '|---|' + '---|' * len(set(r.actor_method for r in results))]
    table = summary(results)
    for rm in dict.fromkeys(r[0] for r in table):
        cells = [f'{m:.2f} +- {s:.2f}' for (r, _, m, s, _) in table if r == rm]
        lines.append(f'| {rm} | ' + ' | '.join(cells) + ' |')
    lines += ['', '| actor | reader | reader k | R^2 | windows |', '|---|---|---|---|---|']
    lines += [f'| {r.actor} | {r.reader} | {r.reader_k} | {r.r2:.3f} | {r.steps} |'
              for r in results]
    stem.with_suffix('.md').write_text('\n'.join(lines) + '\n')


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--actors', nargs='+', required=True, help='checkpoints whose policy acts')
    p.add_argument('--readers', nargs='+', required=True, help='checkpoints that decode')
    p.add_argument('--episodes', type=int, default=2, help='episodes per held-out value')
    p.add_argument('--name', default='cross_reader', help='stem of the result files')
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    readers = {Path(r).name: InferenceModel.load(r) for r in args.readers}
    family = next(iter(readers.values())).family
    spec = get_family(family)
    values = [v for split in HELD_OUT for v in spec.split(split)]
    results = []
    for path in args.actors:
        actor = InferenceModel.load(path, expected_family=family)
        data = actor_transitions(actor, values, args.episodes)
        results += cross(Path(path).name, actor, data, readers)
        read = ', '.join(f'{r.reader} {r.r2:.2f}' for r in results[-len(readers):])
        print(f'{Path(path).name}: {read}', flush=True)
    command = ('PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/cross_reader.py '
               + ' '.join(['--actors', *args.actors, '--readers', *args.readers]))
    write(RESULTS / args.name, results, family, values, args.episodes, command)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
