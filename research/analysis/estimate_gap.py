"""Identification or policy: the return when the parameter estimate is replaced by the truth.

Issue #14 asks the best context method to come within 5 % of `oracle`, and,
where it does not, what would close the gap. For a method whose latent holds
the parameter estimate itself (`up-osi`: the whole latent is OSI's estimate;
`zeus-osi`: its first P coordinates), the gap splits in two by one swap:
feed the policy the TRUE normalised parameter in those coordinates (the rest
of the latent, if any, as inferred) and measure the return again, same
values, same start states. If the return with the truth reaches the
oracle's, the whole gap is the estimate's error, and a better estimator closes
it; if not, the policy itself falls short. For `rma`, whose latent is an
estimate of its teacher's extrinsics z = mu(parameter), the truth is the
teacher's latent for the true parameter (the deployed weights carry mu).

    PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/estimate_gap.py \
        --runs weights/cheetah-run-v1-up-osi --split interpolation

Writes research/results/<name>.md: per run, the mean return at the split's
values with the estimate as inferred and with the truth, the mean estimate
per value, and the mean over runs.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
import sys

import numpy as np
import torch

from sim_node.families import as_values, get_sim_family
from summarize_runs import mean_se   # its folder is on the path when the script runs
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import EpisodeProbe, run_episode

RESULTS = Path(__file__).resolve().parents[1] / 'results'
ESTIMATE_IN_LATENT = ('up-osi', 'zeus-osi')   # methods whose latent starts with the estimate
TEACHER_LATENT = ('rma',)                     # methods whose latent estimates a teacher's


class TrueEstimate(EpisodeProbe):
    """Put the true normalised parameter in the estimate coordinates; keep the rest."""

    def __init__(self, model: InferenceModel, value):
        truth = torch.tensor([as_values(value)], dtype=torch.float32)
        self.normalised = model.method.param.normalise(truth)[0].numpy()

    def latent(self, latent):
        out = np.array(latent, np.float32, copy=True)
        out[:self.normalised.size] = self.normalised
        return out


class TeacherLatent(EpisodeProbe):
    """Replace the whole latent by the teacher's extrinsics for the true parameter."""

    def __init__(self, model: InferenceModel, value):
        truth = torch.tensor([as_values(value)], dtype=torch.float32)
        with torch.no_grad():
            self.teacher = model.method.teacher(truth)[0].numpy().astype(np.float32)

    def latent(self, latent):  # noqa: ARG002 (EpisodeProbe's signature: replaced whole)
        return self.teacher.copy()


def truth_probe(model: InferenceModel, value) -> EpisodeProbe:
    """Return the probe that gives `model`'s policy the truth in place of its estimate."""
    if model.method_name in TEACHER_LATENT:
        return TeacherLatent(model, value)
    return TrueEstimate(model, value)


@dataclass(frozen=True)
class ValueFigures:
    """Mean over episodes at one parameter value."""

    value: float
    inferred: float        # return, the estimate as the method infers it
    truth: float           # return, the estimate replaced by the true parameter
    mean_estimate: float   # decoded estimate over the steps with a full window


def value_figures(model: InferenceModel, value, episodes: int) -> ValueFigures:
    """Run `episodes` deterministic episodes (seeds 0..) each way at one value."""
    inferred = [run_episode(model, model.family, value, seed) for seed in range(episodes)]
    truth = [run_episode(model, model.family, value, seed, probe=truth_probe(model, value))
             for seed in range(episodes)]
    estimate = np.mean(np.concatenate([r.estimates[model.k:] for r in inferred]))
    return ValueFigures(float(value), float(np.mean([r.episode_return for r in inferred])),
                        float(np.mean([r.episode_return for r in truth])), float(estimate))


def run_figures(path: Path, split: str, episodes: int) -> tuple[InferenceModel, list]:
    """Load one run's weights and measure every value of `split`."""
    model = InferenceModel.load(path)
    if model.method_name not in ESTIMATE_IN_LATENT + TEACHER_LATENT:
        raise SystemExit(f'{path}: {model.method_name} has no estimate in its latent '
                         f'(one of {", ".join(ESTIMATE_IN_LATENT + TEACHER_LATENT)} is needed)')
    values = get_sim_family(model.family).split(split)
    if not values:
        raise SystemExit(f'{model.family} has no {split} values')
    return model, [value_figures(model, v, episodes) for v in values]


def run_means(figs: list) -> tuple[float, float]:
    """Return one run's mean return over the split's values: (inferred, truth)."""
    return (float(np.mean([f.inferred for f in figs])), float(np.mean([f.truth for f in figs])))


def render(rows: dict, split: str, episodes: int, argv: list) -> str:
    """Markdown: the per-run table, the per-value table, and the mean over runs."""
    lines = [f'# The estimate replaced by the truth ({split})', '',
             '`PYTHONPATH=. OMP_NUM_THREADS=1 python research/analysis/estimate_gap.py '
             f'{" ".join(argv)}`; '
             f'{episodes} deterministic episodes per value (seeds 0..{episodes - 1}), '
             'the same start states both ways.', '',
             '| run | method | return, estimate inferred | return, true parameter | '
             'gained by the truth |', '|---|---|---|---|---|']
    for run, (method, figs) in rows.items():
        inferred, truth = run_means(figs)
        lines.append(f'| {run} | {method} | {inferred:.1f} | {truth:.1f} | '
                     f'{truth - inferred:.1f} |')
    if len(rows) > 1:
        inferred, truth = zip(*(run_means(figs) for _, figs in rows.values()), strict=True)
        lines.append(f'| mean +- SE over {len(rows)} runs | | {mean_se(list(inferred), 1)} | '
                     f'{mean_se(list(truth), 1)} | |')
    lines += ['', '| run | value | mean estimate | return, inferred | return, truth |',
              '|---|---|---|---|---|']
    for run, (_, figs) in rows.items():
        lines += [f'| {run} | {f.value:g} | {f.mean_estimate:.2f} | {f.inferred:.1f} | '
                  f'{f.truth:.1f} |' for f in figs]
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--runs', nargs='+', type=Path, required=True,
                   help='run or weights directories of up-osi / zeus-osi / rma checkpoints')
    p.add_argument('--split', default='interpolation',
                   choices=('train', 'interpolation', 'extrapolation'))
    p.add_argument('--episodes', type=int, default=2)
    p.add_argument('--name', default='estimate_gap', help='results file name (no suffix)')
    args = p.parse_args(argv)
    rows = {}
    for path in args.runs:
        model, figs = run_figures(path, args.split, args.episodes)
        name = path.parent.name if path.name == 'checkpoint' else path.name   # a run's folder
        rows[name] = (model.method_name, figs)
        inferred, truth = run_means(figs)
        print(f'{name}: inferred {inferred:.1f}, truth {truth:.1f}', flush=True)
    out = RESULTS / f'{args.name}.md'
    out.write_text(render(rows, args.split, args.episodes, argv))
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
