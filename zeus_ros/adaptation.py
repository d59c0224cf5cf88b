"""Adaptation report: does the context carry the physics, does the policy act on it.

    python -m zeus_ros.adaptation --weights runs/w --episodes 2 --json report.json

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
4. **context use**, at the extrapolation values (where a context is needed if
   anywhere; at the interpolation values for a family without extrapolation):
   the return when the latent is zeroed, frozen at the latent of another
   value's episode, or inferred from window transitions simulated
   under another value (same states and actions, other physics). The other
   value is the train value farthest from the true one. A policy that ignores
   the parameter shows no gap: the report says so.

A method without a latent (`sac`) has no estimate and no context to perturb:
those sections are reported as not applicable.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, field
import json
from pathlib import Path
import sys

import numpy as np
from scipy.stats import spearmanr

from sim_node.env import ParamEnv
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.evaluate import EpisodeProbe, run_episode

HELD_OUT = ('interpolation', 'extrapolation')
COVERED = 0.7


@dataclass
class ReportConfig:
    """What the report runs."""

    episodes: int = field(default=2, metadata={'help': 'episodes per value and condition'})
    seed: int = field(default=0, metadata={'help': 'first episode seed (seed + e per episode)'})
    max_steps: int = field(default=1000, metadata={'help': 'steps per episode'})
    swap_step: int = field(default=300, metadata={'help': 'step of the live swap'})
    swap_steps: int = field(default=600, metadata={'help': 'length of a swap episode'})


@dataclass
class SplitReturn:
    """Return on one split: mean over its values, standard error over values."""

    split: str
    mean: float
    sem: float
    per_value: dict[str, float]


@dataclass
class Identification:
    """How well the decoded estimate follows the true value on held-out values."""

    r2_per_step: float
    spearman_episode_means: float
    per_value_mean_estimate: dict[str, float]


@dataclass
class SwapResponse:
    """Steps after a live swap until the estimate covered 70 % of the change."""

    from_value: float
    to_value: float
    steps_to_70pct: int | None


@dataclass
class ContextUse:
    """Mean return at the extrapolation values, intact and with the context perturbed."""

    split: str      # where it was measured: extrapolation, or interpolation if a family has none
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

    def to_json(self) -> str:
        """Indented JSON text of the report."""
        return json.dumps(asdict(self), indent=2)


# -- probes that perturb the context --------------------------------------------
class ZeroedContext(EpisodeProbe):
    """The policy sees the zero latent (the empty-window latent) at every step."""

    def __init__(self, model: InferenceModel):
        self.zeros = np.zeros(model.context_dim, np.float32)

    def latent(self, latent):
        return self.zeros


class FrozenContext(EpisodeProbe):
    """The policy sees one fixed latent taken from an episode at another value."""

    def __init__(self, latent: np.ndarray, other_value: float):
        self.frozen, self.other = latent.astype(np.float32), other_value

    def true_param(self, env):
        return self.other

    def latent(self, latent):
        return self.frozen


class OtherPhysicsWindow(EpisodeProbe):
    """The window holds (s, a, r', s'') simulated from the same s and a at another value."""

    def __init__(self, family: str, other_value: float, max_steps: int,
                 reward_in_obs: bool = False):
        self.shadow = ParamEnv(family, other_value, seed=0, episode_steps=max_steps,
                               reward_in_obs=reward_in_obs)
        self.other = other_value
        self.counterfactual = None

    def true_param(self, env):
        return self.other

    def before_step(self, env, action):
        self.shadow.copy_state_from(env)
        self.counterfactual = self.shadow.step(action)

    def window_transition(self, result):
        return self.counterfactual.reward, self.counterfactual.observation


class SpeedRecorder(EpisodeProbe):
    """Records the robot's forward speed after every step; changes nothing it sees."""

    def __init__(self):
        self.env, self.speeds = None, []

    def before_step(self, env, action):
        self.env = env

    def window_transition(self, result):
        self.speeds.append(float(self.env.physics.speed()))
        return result.reward, result.observation


# -- measures ----------------------------------------------------------------------
def _episodes(model, value, cfg: ReportConfig, probe_factory=None, **kwargs):
    return [run_episode(model, model.family, value, cfg.seed + e, max_steps=cfg.max_steps,
                        probe=probe_factory() if probe_factory else None, **kwargs)
            for e in range(cfg.episodes)]


def _sem(values) -> float:
    values = np.asarray(values, float)
    return float(values.std(ddof=1) / np.sqrt(values.size)) if values.size > 1 else 0.0


def split_returns(model, spec, cfg: ReportConfig, records: dict) -> list[SplitReturn]:
    """Per-split mean return (and its standard error over values)."""
    out = []
    for split in ('train', *HELD_OUT):
        values = spec.split(split)
        if not values:
            continue
        per_value = {str(v): float(np.mean([r.episode_return for r in records[v]]))
                     for v in values}
        out.append(SplitReturn(split, float(np.mean(list(per_value.values()))),
                               _sem(list(per_value.values())), per_value))
    return out


def r_squared(truth, estimate) -> float:
    """Coefficient of determination of `estimate` for `truth`."""
    truth, estimate = np.asarray(truth, float), np.asarray(estimate, float)
    total = ((truth - truth.mean()) ** 2).sum()
    return float(1.0 - ((truth - estimate) ** 2).sum() / total) if total > 0 else float('nan')


def identification(model, values, records: dict) -> Identification:
    """R^2 over full-window steps and rank correlation of episode means, held-out values."""
    truth, estimate, means, mean_truth = [], [], {}, []
    episode_means = []
    for v in values:
        for rec in records[v]:
            full = rec.estimates[model.k:]
            truth.extend([v] * full.size)
            estimate.extend(full)
            episode_means.append(float(np.mean(full)))
            mean_truth.append(v)
        means[str(v)] = float(np.mean([np.mean(r.estimates[model.k:]) for r in records[v]]))
    rho = spearmanr(mean_truth, episode_means).statistic if len(set(mean_truth)) > 1 else np.nan
    return Identification(r_squared(truth, estimate), float(rho), means)


def steps_to_cover(estimates: np.ndarray, swap_step: int, before: float, after: float):
    """First step count after the swap at which 70 % of the true change is covered."""
    start = float(np.mean(estimates[max(0, swap_step - 50):swap_step]))
    change = after - before
    covered = (estimates[swap_step:] - start) / change >= COVERED
    hits = np.flatnonzero(covered)
    return int(hits[0]) if hits.size else None


def swap_responses(model, spec, cfg: ReportConfig) -> list[SwapResponse]:
    """Live swaps between the extremes of the train and of the extrapolation values."""
    pairs = [(min(spec.train), max(spec.train)), (max(spec.train), min(spec.train))]
    if spec.extrapolation:
        pairs += [(min(spec.extrapolation), max(spec.extrapolation)),
                  (max(spec.extrapolation), min(spec.extrapolation))]
    out = []
    swap_cfg = ReportConfig(1, cfg.seed, cfg.swap_steps, cfg.swap_step, cfg.swap_steps)
    for a, b in pairs:
        rec = _episodes(model, a, swap_cfg, swap_schedule={cfg.swap_step: b})[0]
        out.append(SwapResponse(a, b, steps_to_cover(rec.estimates, cfg.swap_step, a, b)))
    return out


def speed_recorded_episodes(model, values, cfg: ReportConfig) -> tuple[dict, dict]:
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


def velocity_error(spec, speeds: dict) -> VelocityError:
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


def farthest_train_value(spec, value: float) -> float:
    """Return the training value farthest from `value` (the most different physics seen)."""
    return max(spec.train, key=lambda t: abs(t - value))


def context_use(model, spec, cfg: ReportConfig, records: dict) -> ContextUse:
    """Measure returns at the extrapolation values, context intact and perturbed."""
    split = 'extrapolation' if spec.extrapolation else 'interpolation'
    values = spec.split(split)
    rows = {'intact': [], 'zeroed': [], 'frozen_other': [], 'inferred_other': []}
    for v in values:
        other = farthest_train_value(spec, v)
        other_latent = np.mean(_episodes(model, other, cfg)[0].latents[model.k:], axis=0)
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
    model = InferenceModel.load(weights)
    spec = ParamEnv(model.family, seed=0).spec
    values = sorted({v for s in ('train', *HELD_OUT) for v in spec.split(s)})
    velocity = None
    if spec.param_name == 'target_velocity':
        records, speeds = speed_recorded_episodes(model, values, cfg)
        velocity = velocity_error(spec, speeds)
    else:
        records = {v: _episodes(model, v, cfg) for v in values}
    has_context = model.context_dim > 0
    held_out = sorted({v for s in HELD_OUT for v in spec.split(s)})
    return AdaptationReport(
        weights=str(weights), family=model.family, method=model.method_name, k=model.k,
        context_dim=model.context_dim, returns=split_returns(model, spec, cfg, records),
        identification=identification(model, held_out, records) if has_context else None,
        swaps=swap_responses(model, spec, cfg) if has_context else [],
        context_use=context_use(model, spec, cfg, records) if has_context else None,
        velocity_error=velocity)


def print_report(report: AdaptationReport) -> None:
    """Human-readable summary."""
    print(f'{report.family} {report.method} (k={report.k}, latent {report.context_dim}) '
          f'from {report.weights}')
    for r in report.returns:
        print(f'  return {r.split:<14} {r.mean:8.1f} +- {r.sem:5.1f}')
    if report.velocity_error is not None:
        errors = report.velocity_error.mean_per_split
        print('  mean |speed - target|, m/s: ' + ', '.join(
            f'{split} {error:.3f}' for split, error in errors.items()))
    if report.identification is None:
        print('  no latent: identification, swaps and context use do not apply')
        return
    ident = report.identification
    print(f'  decoded estimate, held-out: R^2 {ident.r2_per_step:.3f}, '
          f'Spearman {ident.spearman_episode_means:.3f}')
    for s in report.swaps:
        print(f'  swap {s.from_value:g} -> {s.to_value:g}: 70 % covered after '
              f'{f"{s.steps_to_70pct} steps" if s.steps_to_70pct is not None else "never"}')
    use = report.context_use
    print(f'  {use.split} return: intact {use.intact:.1f}, zeroed {use.zeroed:.1f}, '
          f'frozen at other value {use.frozen_other:.1f}, '
          f'inferred from other physics {use.inferred_other:.1f}')
    print(f'  policy {use.verdict}')


def main(argv=None) -> int:
    """Console entry point (`adaptation_report`)."""
    p = argparse.ArgumentParser(prog='adaptation_report', description=__doc__.split('\n')[0])
    p.add_argument('--weights', required=True, help='checkpoint dir or run dir')
    p.add_argument('--json', type=Path, default=None, help='write the report here')
    defaults = ReportConfig()
    for name, f in ReportConfig.__dataclass_fields__.items():
        p.add_argument(f'--{name.replace("_", "-")}', type=int, default=getattr(defaults, name),
                       help=f.metadata['help'])
    args = p.parse_args(argv)
    cfg = ReportConfig(**{n: getattr(args, n) for n in ReportConfig.__dataclass_fields__})
    try:
        report = build_report(args.weights, cfg)
    except CheckpointError as error:
        print(f'cannot load weights: {error}', file=sys.stderr)
        return 2
    print_report(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(report.to_json())
    return 0


if __name__ == '__main__':
    sys.exit(main())
