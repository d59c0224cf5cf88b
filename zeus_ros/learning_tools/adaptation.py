"""Adaptation report: does the context carry the physics, does the policy act on it.

    python -m zeus_ros.learning_tools.adaptation --weights runs/w --episodes 2 --json report.json

For one checkpoint, with deterministic episodes (`evaluate.run_episode`, the
order of operations of the ROS loop):

1. **returns per split** (train / interpolation / extrapolation): mean over
   values of the per-value mean return, with the standard error over values;
2. **identification** on held-out values (interpolation + extrapolation):
   R^2 of the decoded estimate against the true value over every step whose
   window is full (k transitions), and Spearman's rank correlation between
   each episode's mean estimate and its true value;
3. **live swap**: an episode swaps the value at `--swap-step`; reported are the
   control steps until the estimate has covered 70 % of the true change
   (from its mean over the 50 steps before the swap), or None if it never does;
   and the lag: the steps until the estimate is within 20 % of the new true
   value in log space (|ln(estimate / true)| <= ln 1.2) and stays there for
   5 steps, or None if it never does before the episode ends (or if a true
   value is not positive, where no log-space error exists);
4. **context use**, at the extrapolation values (where a context is needed if
   anywhere; at the interpolation values for a family without extrapolation):
   the return when the latent is zeroed, frozen at the latent of another
   value's episode, or inferred from window transitions simulated
   under another value (same states and actions, other physics). The other
   value is the train value farthest from the true one. A policy that ignores
   the parameter shows no gap: the report says so. The same is measured at
   the train values (`context_use_train`; `--no-context-use-train` skips it),
   since a policy may use the parameter inside its training range and not
   beyond it.

A method without a latent (`sac`) has no estimate and no context to perturb:
those sections are reported as not applicable.

A family with several parameters (Sawyer-Peg-v0's goal x and y) has value
tuples: R^2 and Spearman are reported per parameter (and their mean), a swap
is covered when the estimate has moved 70 % of the way along the change
vector, and the other value is the farthest train value in Euclidean distance.
A task with a success flag also gets its success rate per split.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, field, replace
import json
from pathlib import Path
import sys
from typing import Callable, Iterable, Sequence

import numpy as np
from scipy.stats import spearmanr

from sim_node.env import make_env
from sim_node.family_edits import load_family_file
from sim_node.family_file import FamilyFileError
from sim_node.families import as_values, format_task, get_sim_family, SimFamily, Task
from sim_node.family_env import FamilyEnv
from sim_node.layout import StepResult
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import EpisodeProbe, run_episode

HELD_OUT = ('interpolation', 'extrapolation')
COVERED = 0.7
# The lag after a swap: within 20 % of the true value in log space, held for
# 5 steps, so that an estimate sweeping through the band on its way elsewhere
# (overshooting a swap down, say) does not count as having arrived.
WITHIN = float(np.log(1.2))
WITHIN_HELD = 5


@dataclass
class ReportConfig:
    """What the report runs."""

    episodes: int = field(default=2, metadata={'help': 'episodes per value and condition'})
    seed: int = field(default=0, metadata={'help': 'first episode seed (seed + e per episode)'})
    max_steps: int = field(default=1000, metadata={'help': 'steps per episode'})
    swap_step: int = field(default=300, metadata={'help': 'step of the live swap'})
    swap_steps: int = field(default=600, metadata={'help': 'length of a swap episode'})
    context_use_train: bool = field(default=True, metadata={
        'help': 'also measure context use at the train values (3 perturbed runs per value)'})
    window: int = field(default=0, metadata={
        'help': "deploy with this many transitions per window instead of the checkpoint's k "
                '(0: its k); a shorter window answers a swap sooner, a longer one reads '
                'the parameter from more transitions'})


@dataclass
class SplitReturn:
    """Return on one split: mean over its values, standard error over values."""

    split: str
    mean: float
    sem: float
    per_value: dict[str, float]
    success_rate: float | None = None   # fraction of episodes ending in success, if defined
    # Values of a held-out split that are also train values (cheetah-run-v0's
    # extrapolation prints 1.25, 1.4 and 1.5 in both): left out of its mean.
    left_out: tuple[str, ...] = ()


@dataclass
class Identification:
    """How well the decoded estimate follows the true value on held-out values."""

    r2_per_step: float                  # several parameters: the mean of theirs
    spearman_episode_means: float
    per_value_mean_estimate: dict[str, float | list[float]]
    r2_per_parameter: dict[str, float] = field(default_factory=dict)
    spearman_per_parameter: dict[str, float] = field(default_factory=dict)


@dataclass
class SwapResponse:
    """Steps after a live swap until the estimate covered 70 % of the change."""

    from_value: float | list[float]
    to_value: float | list[float]
    steps_to_70pct: int | None
    # Steps until within 20 % of the new value (log space) for WITHIN_HELD steps;
    # None: never before the episode ends, or a true value <= 0 (no log space).
    steps_to_within_20pct: int | None = None


@dataclass
class ContextUse:
    """Mean return over one split's values, intact and with the context perturbed."""

    split: str      # held-out: extrapolation, or interpolation if a family has none; or train
    intact: float
    zeroed: float
    frozen_other: float
    inferred_other: float
    largest_gap: float
    verdict: str


@dataclass
class VelocityError:
    """Target-velocity families: mean |speed - target| over an episode's steps, per target."""

    per_value: dict[str, float]
    mean_per_split: dict[str, float]


@dataclass
class AdaptationReport:
    """Everything the report measured, JSON-ready."""

    weights: str
    family: str
    method: str
    k: int
    context_dim: int
    returns: list[SplitReturn]
    identification: Identification | None
    swaps: list[SwapResponse]
    context_use: ContextUse | None
    velocity_error: VelocityError | None = None
    context_use_train: ContextUse | None = None   # the same measure at the train values

    def to_json(self) -> str:
        """Indented JSON text of the report."""
        return json.dumps(asdict(self), indent=2)


# -- probes that perturb the context --------------------------------------------
class ZeroedContext(EpisodeProbe):
    """The policy sees the zero latent (the empty-window latent) at every step."""

    def __init__(self, model: InferenceModel):
        self.zeros = np.zeros(model.context_dim, np.float32)

    def latent(self, latent: np.ndarray) -> np.ndarray:  # noqa: ARG002 (EpisodeProbe's signature)
        return self.zeros


class FrozenContext(EpisodeProbe):
    """The policy sees one fixed latent taken from an episode at another value."""

    def __init__(self, latent: np.ndarray, other_value: Task):
        self.frozen, self.other = latent.astype(np.float32), other_value

    def true_param(self, env: FamilyEnv) -> float | tuple[float, ...]:  # noqa: ARG002 (EpisodeProbe's signature)
        return self.other

    def latent(self, latent: np.ndarray) -> np.ndarray:  # noqa: ARG002 (EpisodeProbe's signature)
        return self.frozen


class OtherPhysicsWindow(EpisodeProbe):
    """The window holds (s, a, r', s'') simulated from the same s and a at another value."""

    def __init__(self, family: str, other_value: Task, max_steps: int,
                 reward_in_obs: bool = False):
        self.shadow = make_env(family, as_values(other_value), seed=0, episode_steps=max_steps,
                               reward_in_obs=reward_in_obs)
        self.other = other_value
        self.counterfactual = None

    def true_param(self, env: FamilyEnv) -> float | tuple[float, ...]:  # noqa: ARG002 (EpisodeProbe's signature)
        return self.other

    def before_step(self, env: FamilyEnv, action: np.ndarray) -> None:
        self.shadow.copy_state_from(env)
        self.counterfactual = self.shadow.step(action)

    def window_transition(self, result: StepResult) -> tuple[float, np.ndarray]:  # noqa: ARG002 (EpisodeProbe's signature)
        return self.counterfactual.reward, self.counterfactual.observation


class SpeedRecorder(EpisodeProbe):
    """Records the robot's forward speed after every step; changes nothing it sees."""

    def __init__(self):
        self.env, self.speeds = None, []

    def before_step(self, env: FamilyEnv, action: np.ndarray) -> None:  # noqa: ARG002 (EpisodeProbe's signature)
        self.env = env

    def window_transition(self, result: StepResult) -> tuple[float, np.ndarray]:
        self.speeds.append(float(self.env.physics.speed()))
        return result.reward, result.observation


# -- measures ----------------------------------------------------------------------
def _episodes(model: InferenceModel, value: Task, cfg: ReportConfig,
              probe_factory: Callable[[], EpisodeProbe] | None = None, **kwargs):
    return [run_episode(model, model.family, value, cfg.seed + e, max_steps=cfg.max_steps,
                        probe=probe_factory() if probe_factory else None, **kwargs)
            for e in range(cfg.episodes)]


def _sem(values: Sequence[float]) -> float:
    values = np.asarray(values, float)
    return float(values.std(ddof=1) / np.sqrt(values.size)) if values.size > 1 else 0.0


def value_key(value: Task) -> str:
    """Return a value as the report's keys name it: str(v), or '0.44 -0.07' for a tuple."""
    return str(value) if isinstance(value, float | int) else format_task(value)


def split_returns(spec: SimFamily, records: dict) -> list[SplitReturn]:
    """Per-split mean return (and its standard error over values), and success rate."""
    out = []
    for split in ('train', *HELD_OUT):
        values = spec.split(split) if split == 'train' else held_out_values(spec, split)
        if not values:
            continue
        per_value = {value_key(v): float(np.mean([r.episode_return for r in records[v]]))
                     for v in values}
        successes = [r.success for v in values for r in records[v] if r.success is not None]
        left_out = tuple(value_key(v) for v in spec.split(split) if v not in values)
        out.append(SplitReturn(split, float(np.mean(list(per_value.values()))),
                               _sem(list(per_value.values())), per_value,
                               float(np.mean(successes)) if successes else None, left_out))
    return out


def held_out_values(spec: SimFamily, split: str) -> tuple:
    """Return a split's values that are not also train values (held-out: never trained on)."""
    train = set(spec.split('train'))
    return tuple(v for v in spec.split(split) if v not in train)


def r_squared(truth: np.ndarray, estimate: np.ndarray) -> float:
    """Coefficient of determination of `estimate` for `truth`."""
    truth, estimate = np.asarray(truth, float), np.asarray(estimate, float)
    total = ((truth - truth.mean()) ** 2).sum()
    return float(1.0 - ((truth - estimate) ** 2).sum() / total) if total > 0 else float('nan')


def identification(model: InferenceModel, values: Sequence[Task],
                   records: dict) -> Identification:
    """R^2 over full-window steps and rank correlation of episode means, held-out values.

    Per parameter; the headline figures are those of the one parameter, or
    the mean over several.
    """
    count = len(model.param_names)
    truth, estimate, means, mean_truth, episode_means = [], [], {}, [], []
    for v in values:
        for rec in records[v]:
            full = np.asarray(rec.estimates[model.k:], float).reshape(-1, count)
            truth.append(np.tile(as_values(v), (len(full), 1)))
            estimate.append(full)
            episode_means.append(full.mean(axis=0))
            mean_truth.append(as_values(v))
        mean = np.mean(episode_means[-len(records[v]):], axis=0)
        means[value_key(v)] = float(mean[0]) if count == 1 else [float(m) for m in mean]
    truth, estimate = np.concatenate(truth), np.concatenate(estimate)
    mean_truth, episode_means = np.asarray(mean_truth), np.asarray(episode_means)
    r2 = {n: r_squared(truth[:, i], estimate[:, i]) for i, n in enumerate(model.param_names)}
    rho = {n: float(spearmanr(mean_truth[:, i], episode_means[:, i]).statistic)
           if len(set(mean_truth[:, i])) > 1 else float('nan')
           for i, n in enumerate(model.param_names)}
    return Identification(float(np.mean(list(r2.values()))), float(np.mean(list(rho.values()))),
                          means, r2, rho)


def steps_to_cover(estimates: np.ndarray, swap_step: int, before: Task,
                   after: Task) -> int | None:
    """First step count after the swap at which 70 % of the true change is covered.

    For several parameters, the estimate's move is projected on the change vector.
    """
    change = np.asarray(as_values(after)) - np.asarray(as_values(before))
    estimates = np.asarray(estimates, float).reshape(len(estimates), change.size)
    start = np.mean(estimates[max(0, swap_step - 50):swap_step], axis=0)
    covered = (estimates[swap_step:] - start) @ change / (change @ change) >= COVERED
    hits = np.flatnonzero(covered)
    return int(hits[0]) if hits.size else None


def steps_to_within(estimates: np.ndarray, swap_step: int, after: Task,
                    end: int | None = None) -> int | None:
    """Count the steps after the swap until the estimate is within 20 % of `after` (log space).

    Counted from the swap step (0: the first estimate under the new value is
    already within), until WITHIN_HELD steps in a row are within (every
    parameter, for several), the run wholly before `end`; None if there is no
    such run, or if a true value is not positive. A non-positive estimate has
    no logarithm and is never within.
    """
    truth = np.asarray(as_values(after), float)
    if np.any(truth <= 0):
        return None
    estimates = np.asarray(estimates, float).reshape(len(estimates), truth.size)
    with np.errstate(divide='ignore', invalid='ignore'):   # estimates <= 0: NaN / -inf
        error = np.abs(np.log(estimates[swap_step:end]) - np.log(truth))
    within = np.all(error <= WITHIN, axis=1)
    if within.size < WITHIN_HELD:
        return None
    held = np.lib.stride_tricks.sliding_window_view(within, WITHIN_HELD).all(axis=1)
    hits = np.flatnonzero(held)
    return int(hits[0]) if hits.size else None


def _farthest_pair(values: Sequence[Task]) -> tuple:
    """Return the two values farthest apart (a one-parameter split: its extremes)."""
    pairs = [(a, b) for a in values for b in values]
    return max(pairs, key=lambda p: _distance(*p))


def _distance(a: Task, b: Task) -> float:
    return float(np.linalg.norm(np.subtract(as_values(a), as_values(b))))


def _json_value(value: Task) -> float | list[float]:
    return value if isinstance(value, float | int) else list(as_values(value))


def swap_responses(model: InferenceModel, spec: SimFamily,
                   cfg: ReportConfig) -> list[SwapResponse]:
    """Live swaps between the extremes of the train and of the extrapolation values."""
    a, b = _farthest_pair(spec.train)
    pairs = [(a, b), (b, a)]
    if spec.extrapolation:
        a, b = _farthest_pair(spec.extrapolation)
        pairs += [(a, b), (b, a)]
    out = []
    steps = min(cfg.swap_steps, spec.episode_steps)
    swap_step = min(cfg.swap_step, steps // 2)
    swap_cfg = ReportConfig(1, cfg.seed, steps, swap_step, steps)
    for a, b in pairs:
        rec = _episodes(model, a, swap_cfg, swap_schedule={swap_step: b})[0]
        out.append(SwapResponse(_json_value(a), _json_value(b),
                                steps_to_cover(rec.estimates, swap_step, a, b),
                                steps_to_within(rec.estimates, swap_step, b)))
    return out


def speed_recorded_episodes(model: InferenceModel, values: Iterable[Task],
                            cfg: ReportConfig) -> tuple[dict, dict]:
    """Run the report's episodes per value, recording the robot's speed at every step.

    The recorder changes nothing the policy sees, so the records are those of
    `_episodes`: the velocity error costs no episodes of its own.
    """
    records, speeds = {}, {}
    for v in values:
        recorders = [SpeedRecorder() for _ in range(cfg.episodes)]
        records[v] = [run_episode(model, model.family, v, cfg.seed + e, max_steps=cfg.max_steps,
                                  probe=recorder) for e, recorder in enumerate(recorders)]
        speeds[v] = np.concatenate([r.speeds for r in recorders])
    return records, speeds


def velocity_error(spec: SimFamily, speeds: dict) -> VelocityError:
    """Return the mean absolute speed error per target value and per split.

    The issue's figure for cheetah-run-v1, whose return is negative by construction.
    """
    per_value, per_split = {}, {}
    for split in ('train', *HELD_OUT):
        errors = [float(np.mean(np.abs(speeds[v] - v))) for v in spec.split(split)]
        per_value.update({str(v): e for v, e in zip(spec.split(split), errors, strict=True)})
        if errors:
            per_split[split] = float(np.mean(errors))
    return VelocityError(per_value, per_split)


def farthest_train_value(spec: SimFamily, value: Task) -> float | tuple[float, ...]:
    """Return the training value farthest from `value` (the most different physics seen)."""
    return max(spec.train, key=lambda t: _distance(t, value))


def held_out_split(spec: SimFamily) -> str:
    """Name the split where a context is needed if anywhere: extrapolation, else interpolation."""
    return 'extrapolation' if spec.extrapolation else 'interpolation'


def context_use(model: InferenceModel, spec: SimFamily, cfg: ReportConfig, records: dict,
                split: str) -> ContextUse:
    """Measure returns at one split's values, context intact and perturbed."""
    values = spec.split(split) if split == 'train' else held_out_values(spec, split)
    rows = {'intact': [], 'zeroed': [], 'frozen_other': [], 'inferred_other': []}
    for v in values:
        other = farthest_train_value(spec, v)
        other_latent = np.mean(records[other][0].latents[model.k:], axis=0)   # a train value
        probes = {'zeroed': lambda: ZeroedContext(model),
                  'frozen_other': lambda lat=other_latent, o=other: FrozenContext(lat, o),
                  'inferred_other': lambda o=other: OtherPhysicsWindow(
                      model.family, o, cfg.max_steps, model.reward_in_observation)}
        rows['intact'].append(np.mean([r.episode_return for r in records[v]]))
        for name, factory in probes.items():
            rows[name].append(np.mean([r.episode_return
                                       for r in _episodes(model, v, cfg, factory)]))
    means = {k: float(np.mean(v)) for k, v in rows.items()}
    gap = max(means['intact'] - means[k] for k in ('zeroed', 'frozen_other', 'inferred_other'))
    return ContextUse(split, **means, largest_gap=gap, verdict=_verdict(means['intact'], gap))


def _verdict(intact: float, gap: float) -> str:
    if gap > 0.05 * max(abs(intact), 1.0):
        return f'acts on its context: perturbing it costs up to {gap:.1f} of return'
    return f'does not act on its context: no perturbation costs more than {max(gap, 0):.1f}'


def build_report(weights: str, cfg: ReportConfig) -> AdaptationReport:
    """Run every measure for one checkpoint."""
    if cfg.window < 0:   # refused before the weights are loaded
        raise ValueError(f"window must be >= 0 (0: the checkpoint's k), got {cfg.window}")
    model = InferenceModel.load(weights)
    if cfg.window:   # the encoders pool over a masked window of any length
        model.k = cfg.window
    spec = get_sim_family(model.family)
    # No episode longer than the family's own (Sawyer: 40 steps, the others 1000).
    cfg = replace(cfg, max_steps=min(cfg.max_steps, spec.episode_steps))
    values = sorted({v for s in ('train', *HELD_OUT) for v in spec.split(s)})
    velocity = None
    if spec.param_names == ('target_velocity',):
        records, speeds = speed_recorded_episodes(model, values, cfg)
        velocity = velocity_error(spec, speeds)
    else:
        records = {v: _episodes(model, v, cfg) for v in values}
    has_context = model.context_dim > 0
    held_out = sorted({v for s in HELD_OUT for v in held_out_values(spec, s)})
    measure_train = has_context and cfg.context_use_train
    return AdaptationReport(
        weights=str(weights), family=model.family, method=model.method_name, k=model.k,
        context_dim=model.context_dim, returns=split_returns(spec, records),
        identification=identification(model, held_out, records) if has_context else None,
        swaps=swap_responses(model, spec, cfg) if has_context else [],
        context_use=(context_use(model, spec, cfg, records, held_out_split(spec))
                     if has_context else None),
        velocity_error=velocity,
        context_use_train=(context_use(model, spec, cfg, records, 'train')
                           if measure_train else None))


def print_report(report: AdaptationReport) -> None:
    """Human-readable summary."""
    print(f'{report.family} {report.method} (k={report.k}, latent {report.context_dim}) '
          f'from {report.weights}')
    for r in report.returns:
        success = '' if r.success_rate is None else f', success {r.success_rate:.2f}'
        left_out = (f' (without {", ".join(r.left_out)}: also train values)'
                    if r.left_out else '')
        print(f'  return {r.split:<14} {r.mean:8.1f} +- {r.sem:5.1f}{success}{left_out}')
    if report.velocity_error is not None:
        errors = report.velocity_error.mean_per_split
        print('  mean |speed - target|, m/s: ' + ', '.join(
            f'{split} {error:.3f}' for split, error in errors.items()))
    if report.identification is None:
        print('  no latent: identification, swaps and context use do not apply')
        return
    ident = report.identification
    print(f'  decoded estimate, held-out (values not in train): R^2 {ident.r2_per_step:.3f}, '
          f'Spearman {ident.spearman_episode_means:.3f}')
    if len(ident.r2_per_parameter) > 1:
        print('  per parameter: ' + ', '.join(
            f'{n} R^2 {r2:.3f} Spearman {ident.spearman_per_parameter[n]:.3f}'
            for n, r2 in ident.r2_per_parameter.items()))
    for s in report.swaps:
        positive = np.all(np.asarray(s.to_value, float) > 0)
        print(f'  swap {format_task(s.from_value)} -> {format_task(s.to_value)}: '
              f'70 % covered {_after(s.steps_to_70pct)}, within 20 % (log space, '
              f'{WITHIN_HELD} steps) {_after(s.steps_to_within_20pct) if positive else "n/a"}')
    for use in (report.context_use, report.context_use_train):
        if use is None:
            continue
        print(f'  {use.split} return: intact {use.intact:.1f}, zeroed {use.zeroed:.1f}, '
              f'frozen at other value {use.frozen_other:.1f}, '
              f'inferred from other physics {use.inferred_other:.1f}')
        print(f'  at the {use.split} values the policy {use.verdict}')


def _after(steps: int | None) -> str:
    return 'never' if steps is None else f'after {steps} steps'


def main(argv: list[str] | None = None) -> int:
    """Console entry point (`adaptation_report`)."""
    p = argparse.ArgumentParser(prog='adaptation_report', description=__doc__.split('\n')[0])
    p.add_argument('--weights', required=True, help='checkpoint dir or run dir')
    p.add_argument('--json', type=Path, default=None, help='write the report here')
    p.add_argument('--family-file', type=Path, default=None,
                   help="the checkpoint's family file: checked to be the one it recorded "
                        '(not needed: a checkpoint carries its family file)')
    defaults = ReportConfig()
    for name, f in ReportConfig.__dataclass_fields__.items():
        flag, default = f'--{name.replace("_", "-")}', getattr(defaults, name)
        if isinstance(default, bool):
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=default,
                           help=f.metadata['help'])
        else:
            p.add_argument(flag, type=int, default=default, help=f.metadata['help'])
    args = p.parse_args(argv)
    cfg = ReportConfig(**{n: getattr(args, n) for n in ReportConfig.__dataclass_fields__})
    try:
        if args.family_file is not None:
            load_family_file(args.family_file)   # a different file of the same name: refused
        report = build_report(args.weights, cfg)
    except FamilyFileError as error:
        print(f'adaptation_report: {error}', file=sys.stderr)
        return 1
    except CheckpointError as error:
        print(f'cannot load weights: {error}', file=sys.stderr)
        return 2
    except ValueError as error:
        print(f'adaptation_report: {error}', file=sys.stderr)
        return 2
    print_report(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(report.to_json())
    return 0


if __name__ == '__main__':
    sys.exit(main())
