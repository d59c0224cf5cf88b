"""Evaluate a checkpoint in process, exactly as the ROS loop runs the policy.

    python -m zeus_ros.learning_tools.evaluate --weights runs/w0 --split extrapolation --episodes 2

`run_episode` is the reference order of operations that the ROS nodes follow
(and that the ROS-vs-in-process equality test compares against):

    obs = env.reset(seed)                       # window cleared
    each step:
        rows, mask = window.arrays()
        latent = model.context(rows, mask)      # float32 (what the context node publishes;
                                                # privileged methods also get the true value)
        action = model.act(obs, latent)         # float64 in [-1, 1]
        result = env.step(action)
        window.push(obs, action, result.reward, result.observation)
        obs = result.observation
    at the episode end (truncation, terminal or instability) the window is cleared.

An optional swap schedule {step: value} calls `env.set_values(value)` before
that step's context is computed (a live parameter swap; the window is kept).
A value is a number for a one-parameter family, a tuple for one with several
(Sawyer-Peg-v0's goal); records then hold one column per parameter.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
import sys
from typing import Sequence

import numpy as np

from sim_node.env import make_env
from sim_node.families import as_values, format_task, get_sim_family, SPLITS, Task
from sim_node.family_env import FamilyEnv
from sim_node.layout import StepResult
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.deploy.inference import DeployedModel, InferenceModel
from zeus_ros.core.window import ContextWindow


@dataclass
class EpisodeRecord:
    """Per-step records of one episode (arrays stacked over steps)."""

    observations: np.ndarray  # [T, obs_dim] observation the action was chosen at
    latents: np.ndarray       # [T, context_dim] float32
    actions: np.ndarray       # [T, action_dim] float64
    rewards: np.ndarray       # [T]
    param_values: np.ndarray  # [T] parameter in force at each step ([T, P] for several)
    estimates: np.ndarray     # [T] decoder's parameter estimate at each step ([T, P])
    episode_return: float = 0.0
    instability: list = field(default_factory=list)
    success: bool | None = None   # the task's success flag at the last step, where it has one


class EpisodeProbe:
    """Hooks on what the context sees in `run_episode`; this base changes nothing.

    Subclasses (zeus_ros.learning_tools.adaptation) zero or freeze the latent, or feed the
    window transitions simulated under another parameter value, to measure
    whether a policy acts on its context.
    """

    def true_param(self, env: FamilyEnv) -> float | tuple[float, ...]:
        """Return the true value(s) a privileged method is given."""
        return env.param_values

    def latent(self, latent: np.ndarray) -> np.ndarray:
        """Return the latent the policy acts on."""
        return latent

    def before_step(self, env: FamilyEnv, action: np.ndarray) -> None:
        """See the state and action just before the env steps."""

    def window_transition(self, result: StepResult) -> tuple[float, np.ndarray]:
        """(r, s') pushed into the window for the step just taken."""
        return result.reward, result.observation


class _Recorder:
    def __init__(self):
        self.rows = {n: [] for n in ('obs', 'lat', 'act', 'rew', 'val', 'est')}
        self.instability = []

    def add(self, **values) -> None:
        for name, value in values.items():
            self.rows[name].append(value)

    def record(self) -> EpisodeRecord:
        r = self.rows
        return EpisodeRecord(np.asarray(r['obs']), np.asarray(r['lat'], np.float32),
                             np.asarray(r['act']), np.asarray(r['rew']), np.asarray(r['val']),
                             np.asarray(r['est']), float(np.sum(r['rew'])), self.instability)


def model_env(model: DeployedModel, value: Task | None = None, seed: int | None = 0,
              family: str | None = None, **kwargs) -> FamilyEnv:
    """Make an env (of the model's family by default) observing what the model reads."""
    return make_env(family or model.family, None if value is None else as_values(value),
                    seed=seed, reward_in_obs=model.reward_in_observation, **kwargs)


def _episode_env(model: DeployedModel, family: str, value: Task | None, seed: int,
                 max_steps: int | None, env: FamilyEnv | None) -> FamilyEnv:
    if env is None:
        kwargs = {} if max_steps is None else {'episode_steps': max_steps}
        return model_env(model, value, seed, family, **kwargs)
    if env.obs_dim != model.obs_dim:
        raise ValueError(f'the env observes {env.obs_dim} values, the weights '
                         f'{model.obs_dim} (reward in the observation: '
                         f'{model.reward_in_observation})')
    if tuple(env.param_values) != as_values(value):
        env.set_values(as_values(value))
    return env


def run_episode(model: DeployedModel, family: str, value: Task | None, seed: int,
                swap_schedule: dict | None = None, max_steps: int | None = None,
                env: FamilyEnv | None = None, probe: EpisodeProbe | None = None) -> EpisodeRecord:
    """Run one deterministic episode in the ROS loop's order; return per-step records."""
    env = _episode_env(model, family, value, seed, max_steps, env)
    probe = probe or EpisodeProbe()
    window = ContextWindow(model.k, env.obs_dim, env.action_dim)
    obs = env.reset(seed=seed)
    swaps = dict(swap_schedule or {})
    rec = _Recorder()
    step, one = 0, len(model.param_names) == 1   # one parameter: records hold numbers
    while True:
        if step in swaps:
            env.set_values(as_values(swaps[step]))
        rows, mask = window.arrays()
        latent = probe.latent(model.context(rows, mask, probe.true_param(env)))
        action = model.act(obs, latent)
        probe.before_step(env, action)
        result = env.step(action)
        estimates = model.decode_values(latent)
        rec.add(obs=obs, lat=latent, act=action, rew=result.reward,
                val=env.param_values[0] if one else tuple(env.param_values),
                est=estimates[0] if one else estimates)
        step += 1
        if result.instability:
            rec.instability.append((step, result.instability))
            break
        window.push(obs, action, *probe.window_transition(result))
        obs = result.observation
        if result.truncated or result.terminal:
            break
    record = rec.record()
    record.success = getattr(result, 'success', None)
    return record


def evaluate(model: InferenceModel, values: Sequence[Task], episodes: int, seed: int,
             max_steps: int | None = None) -> list[dict]:
    """Mean/std return, mean decoder estimate(s) and, where the task has one, success rate.

    `mean_estimate` is a number for a one-parameter family, a tuple (one per
    parameter) for one with several; `success_rate` is None without a success flag.
    """
    rows = []
    for v in values:
        recs = [run_episode(model, model.family, v, seed + e, max_steps=max_steps)
                for e in range(episodes)]
        returns = [r.episode_return for r in recs]
        successes = [r.success for r in recs if r.success is not None]
        rows.append({'value': v, 'mean_return': float(np.mean(returns)),
                     'std_return': float(np.std(returns)), 'episodes': episodes,
                     'mean_estimate': _mean_estimate(model, recs),
                     'success_rate': float(np.mean(successes)) if successes else None})
    return rows


def _mean_estimate(model: InferenceModel, recs: list[EpisodeRecord]):
    """Mean estimate over the steps with a full window: a number, or one per parameter."""
    full = np.concatenate([r.estimates[model.k:] for r in recs])
    count = len(model.param_names)
    mean = np.mean(full, axis=0) if len(full) else np.full(count, math.nan)
    values = np.asarray(mean, dtype=np.float64).reshape(count)
    return float(values[0]) if count == 1 else tuple(float(x) for x in values)


def main(argv: list[str] | None = None) -> int:
    """Console entry point (`eval`)."""
    p = argparse.ArgumentParser(prog='eval', description=__doc__.split('\n')[0])
    p.add_argument('--weights', required=True, help='checkpoint dir or run dir')
    p.add_argument('--split', default='extrapolation', choices=SPLITS)
    p.add_argument('--episodes', type=int, default=1)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--values', type=float, nargs='*', default=None,
                   help='parameter values (default: those of --split)')
    p.add_argument('--max-steps', type=int, default=None, help='episode length cap')
    args = p.parse_args(argv)
    try:
        model = InferenceModel.load(args.weights)
    except CheckpointError as error:
        print(f'cannot load weights: {error}', file=sys.stderr)
        return 2
    values = args.values if args.values else get_sim_family(model.family).split(args.split)
    if not values:
        print(f'{model.family} has no {args.split} values', file=sys.stderr)
        return 2
    print(f'family {model.family} ({model.meta.param_name}), checkpoint timestep '
          f'{model.meta.steps.timestep}, split {args.split if not args.values else "custom"}'
          f', {args.episodes} episode(s) per value, seed {args.seed}')
    print(f'{"value":>20} {"mean_return":>12} {"std":>8} {"decoded":>20} {"success":>8}')
    rows = evaluate(model, values, args.episodes, args.seed, args.max_steps)
    for r in rows:
        success = '' if r['success_rate'] is None else f'{r["success_rate"]:.2f}'
        print(f'{format_task(r["value"]):>20} {r["mean_return"]:>12.2f} '
              f'{r["std_return"]:>8.2f} {format_task(r["mean_estimate"]):>20} {success:>8}')
    print(f'{"mean":>20} {np.mean([r["mean_return"] for r in rows]):>12.2f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
