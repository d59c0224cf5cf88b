"""Measure which window reader extrapolates a family's parameter beyond the train range.

Issue #14's R^2 >= 0.9 is on held-out lengths, and on cheetah-run-v0 most of
them lie outside the training range (0.3-0.55 below its 0.6-1.5). The trained
contexts read the interpolation lengths well and saturate below 0.6
(`latent_extrapolation*.md`: the latent leaves its training range there, so it
is not only the decoder). This asks whether another reader of the same
windows would do better: regressors trained DIRECTLY on the normalised length
from full windows at the train values (an upper bound for a supervised
context such as zeus-id's), tested on the held-out values:

- `deep set, MLP head`: psi's shape (one MLP on every row, mean, MLP head);
- `deep set, linear head`: the same rows encoder, a linear read of the mean;
- `relational deep set, MLP head`: each row read with its deviation from the
  window's mean row (`context_encoder=relational`'s form), so a code can
  depend on how a transition differs from the others in its window;
- `ridge, window mean and sd`: a linear model of the mean and standard
  deviation of each row input over the window;
- `ridge, window mean`: the mean only.

Windows: the checkpoint's own deterministic policy acting on its own
context, rows (s, a, r, s' - s) standardised with the train windows'
statistics; fit on start seeds 10-11, tested at 0-1 (the report's). Any
family: `--k` reads windows of another length than the checkpoint's (a
context-free `sac` policy has no window of its own; its k is 5).

    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/length_extrapolation.py \
        --weights research/results/cheetah_v0_50k/cv0-zeus-id-s1
    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/length_extrapolation.py \
        --weights weights/walker-walk-slippery-sac --k 25 --name friction_extrapolation

Writes research/results/length_extrapolation.md (``--name`` to change the stem).
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
from figure4_spearman import windows_for  # noqa: E402
from sim_node.families import get_family  # noqa: E402
from zeus_ros.deploy.inference import InferenceModel  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / 'results'
FIT_SEEDS, TEST_SEED = 10, 0    # windows_for: episode e starts at seed * 100 + e
RIDGE = 1.0


def window_set(model: InferenceModel, values, seed: int, episodes: int, steps: int):
    """Rows (s, a, r, s' - s) of every full window at each value, and the true values."""
    obs_dim = model.obs_dim
    xs, ys = [], []
    for value in values:
        rows = np.stack([r for r, _ in windows_for(model.family, value, episodes, steps, seed,
                                                   model)])
        s, s_next = rows[..., :obs_dim], rows[..., -obs_dim:]
        xs.append(np.concatenate([rows[..., :-obs_dim], s_next - s], -1))
        ys.append(np.full(len(rows), value))
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys)


def r_squared(truth, estimate) -> float:
    return float(1 - np.sum((truth - estimate) ** 2) / np.sum((truth - truth.mean()) ** 2))


def with_deviation(x: torch.Tensor) -> torch.Tensor:
    """Each row beside its deviation from its window's mean row (full windows)."""
    return torch.cat([x, x - x.mean(1, keepdim=True)], -1)


def deep_set(x_fit, y_fit, linear_head: bool, epochs: int, relational: bool = False,
             seed: int = 0):
    """Train psi's shape on the normalised target; return the reading function."""
    torch.manual_seed(seed)
    row_dim = x_fit.shape[-1] * (2 if relational else 1)
    rows = nn.Sequential(nn.Linear(row_dim, 256), nn.ReLU(), nn.Linear(256, 256),
                         nn.ReLU(), nn.Linear(256, 32))
    head = nn.Linear(32, 1) if linear_head else nn.Sequential(
        nn.Linear(32, 64), nn.ReLU(), nn.Linear(64, 1))

    def predict(x):
        return head(rows(with_deviation(x) if relational else x).mean(1)).squeeze(-1)
    xt, yt = torch.from_numpy(x_fit), torch.from_numpy(y_fit.astype(np.float32))
    opt = torch.optim.Adam([*rows.parameters(), *head.parameters()], lr=1e-3)
    for _ in range(epochs):
        for idx in torch.randperm(len(xt)).split(256):
            loss = ((predict(xt[idx]) - yt[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()

    def read(x):
        with torch.no_grad():
            return predict(torch.from_numpy(x)).numpy()
    return read


def ridge(features):
    """Fit a ridge model of window features; return a trainer giving the reading function."""
    def train(x_fit, y_fit):
        design = np.c_[features(x_fit), np.ones(len(x_fit))]
        weights = np.linalg.solve(design.T @ design + RIDGE * np.eye(design.shape[1]),
                                  design.T @ y_fit)
        return lambda x: np.c_[features(x), np.ones(len(x))] @ weights
    return train


def readers(epochs: int) -> dict:
    return {
        'deep set, MLP head': lambda x, y: deep_set(x, y, False, epochs),
        'deep set, linear head': lambda x, y: deep_set(x, y, True, epochs),
        'relational deep set, MLP head': lambda x, y: deep_set(x, y, False, epochs, True),
        'ridge, window mean and sd': ridge(lambda x: np.c_[x.mean(1), x.std(1)]),
        'ridge, window mean': ridge(lambda x: x.mean(1)),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--weights', required=True, help='a run or checkpoint of any family')
    parser.add_argument('--k', type=int, default=None,
                        help="window length (default: the checkpoint's k)")
    parser.add_argument('--episodes', type=int, default=2, help='episodes per value and set')
    parser.add_argument('--steps', type=int, default=1000, help='steps per episode')
    parser.add_argument('--epochs', type=int, default=10)
    parser.add_argument('--name', default='length_extrapolation', help='results file stem')
    args = parser.parse_args(argv)
    model = InferenceModel.load(args.weights)
    model.k = args.k or model.k   # every encoder pools a masked window of any length
    k = model.k
    spec = get_family(model.family)
    held_out = sorted(set(spec.interpolation) | set(spec.extrapolation))
    offset, scale = model.param_offset[0], model.param_scale[0]
    x_fit, y_fit = window_set(model, spec.train, FIT_SEEDS, args.episodes, args.steps)
    x_test, y_test = window_set(model, held_out, TEST_SEED, args.episodes, args.steps)
    mean, sd = x_fit.mean((0, 1)), x_fit.std((0, 1)) + 1e-6   # per row input
    x_fit, x_test = (x_fit - mean) / sd, (x_test - mean) / sd
    estimates = {}
    for name, train in readers(args.epochs).items():
        read = train(x_fit, (y_fit - offset) / scale)
        estimates[name] = read(x_test) * scale + offset
        print(name, f'held-out R^2 {r_squared(y_test, estimates[name]):.3f}', flush=True)
    write(RESULTS / f'{args.name}.md', args, spec, k, y_test, estimates, len(x_fit))
    return 0


def write(path: Path, args, spec, k: int, y_test, estimates: dict, n_fit: int) -> None:
    names = list(estimates)
    inside = (y_test >= min(spec.train)) & (y_test <= max(spec.train))
    lowest = y_test.min()
    lines = [f'# {spec.param_name} beyond the train range ({spec.name}): which reader of the '
             'windows extrapolates?', '',
             f'`PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/length_extrapolation.py '
             f'--weights {args.weights}' + (f' --k {args.k}' if args.k else '')
             + (f' --name {args.name}' if args.name != 'length_extrapolation' else '')
             + f'`: windows of k = {k} from its deterministic '
             f'policy, {args.episodes} episodes x {args.steps} steps per value; {n_fit} '
             f'train-value windows for the fit, {args.epochs} epochs for the deep sets. '
             'R^2 per window.', '',
             '| reader | R^2, held-out (all) | R^2, held-out inside the train span | '
             f'mean estimate at {lowest:g} |', '|---|---|---|---|']
    for name in names:
        est = estimates[name]
        inner = (f'{r_squared(y_test[inside], est[inside]):.3f}'
                 if len(set(y_test[inside])) > 1 else '-')
        lines.append(f'| {name} | {r_squared(y_test, est):.3f} | {inner} | '
                     f'{est[y_test == lowest].mean():.3f} |')
    lines += ['', '| true value | ' + ' | '.join(names) + ' |',
              '|---|' + '---|' * len(names)]
    for value in sorted(set(y_test)):
        at = y_test == value
        lines.append(f'| {value:g} | ' + ' | '.join(f'{estimates[n][at].mean():.3f}'
                                                   for n in names) + ' |')
    path.write_text('\n'.join(lines) + '\n')


if __name__ == '__main__':
    raise SystemExit(main())
