"""Train ZeUS on every training task of a family (Algorithm 1), ROS-free.

    python -m zeus_ros.learning_tools.train --family walker-walk-v0 --steps 50000 --out runs/w0

One TIMESTEP (the unit of ``--steps``, ``--eval-every``, ``--checkpoint-every``)
steps every training task of the family once, in process, then runs one
update; with 8 training tasks that is 8 environment steps. The first
``init_steps`` timesteps (1500, or 10000 for the reward family) act uniformly
at random and do not update. Each task keeps its own `ContextWindow`, cleared
at its episode boundaries; the replay buffer stores, with every transition,
the window before s_t and the one after (see `zeus_ros.core.replay`).

Writes into ``--out``: ``checkpoint/`` (see `zeus_ros.deploy.checkpoint`, replaced
atomically every ``--checkpoint-every`` timesteps and at the end),
``train_log.csv`` (averaged update metrics and speed), ``eval_log.csv`` (one
row per split and parameter value: return and, where the task has one, success
rate), ``episodes.csv`` and TensorBoard scalars in ``tb/``. ``--resume``
continues from ``--out/checkpoint`` with the same config (networks, optimisers,
counters, RNG states and, if saved, the replay buffer); environments start
fresh episodes.
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import asdict, dataclass, field, fields, replace
import os
from pathlib import Path
import signal
import sys
import threading
import time
from typing import Iterable, Sequence, TYPE_CHECKING

import numpy as np
import torch
from tqdm import tqdm

from sim_node.env import make_env
from sim_node.families import (as_values, format_task, get_sim_family, SIM_FAMILIES,
                               SPLITS)
from sim_node.family_edits import load_family_file
from sim_node.family_file import FamilyFileError, FileFamilySpec
from sim_node.family_env import FamilyEnv
from zeus_ros.deploy.checkpoint import (CheckpointError, load_training_checkpoint,
                                 numpy_generator_state, restore_numpy_generator,
                                 save_checkpoint)
from zeus_ros.core.agent import Agent, param_normaliser
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.core.config import (config_types, make_config, preset_note, PROFILES,
                                   refuse_foreign_keys, RUN_KEYS, setting_owners,
                                   settings_groups, SHARED_KEYS, unknown_key_message,
                                   ZeusConfig)
from zeus_ros.core.methods import METHODS
from zeus_ros.core.replay import ReplayBuffer
from zeus_ros.core.settings import add_arguments, parse_text, setting
from zeus_ros.core.window import ContextWindow
from zeus_ros.learning_tools.evaluate import evaluate

if TYPE_CHECKING:
    from types import FrameType

# The train log's first columns; the agent's metric names follow (Agent.metric_names).
RUN_COLUMNS = ('timestep', 'env_steps', 'wall_s', 'env_steps_per_s')


def env_info(env: FamilyEnv) -> dict:
    """Describe the environment layout for the checkpoint metadata (any family's env)."""
    info = {'param_name': ', '.join(env.param_names), 'param_names': env.param_names,
            'joint_names': env.layout.joint_names,
            'position_encoding': env.layout.position_encoding,
            'actuator_names': env.actuator_names, 'train_values': env.spec.train,
            'control_timestep': env.control_timestep,
            'reward_in_observation': env.layout.reward_in_observation,
            'velocity_encoding': env.layout.velocity_encoding,
            # Control range and gear of a MuJoCo motor env (the joint units of a command).
            'actuator_units': getattr(env, 'actuator_units', None)}
    if isinstance(env.spec, FileFamilySpec):
        # The file and its model travel with the weights: a checkpoint loads without them.
        info['family_file'] = {'path': env.spec.origin, 'sha256': env.spec.sha256,
                               'text': env.spec.text, 'model_xml': env.spec.model_xml}
    return info


def family_config(family: str, profile: str = 'cpu', method: str = 'zeus',
                  **overrides) -> ZeusConfig:
    """Build the preset with the family's facts (Table 11's alpha_psi, reward-varying)."""
    spec = get_sim_family(family)
    overrides = {'episode_steps': spec.episode_steps, **overrides}   # Sawyer: Table 9's 40
    if isinstance(spec, FileFamilySpec) and spec.document.training.resample_rate > 0:
        overrides = {'train_swap_prob': spec.document.training.resample_rate, **overrides}
    return make_config(family, profile, method, family_alpha_psi=spec.alpha_psi,
                       reward_varying=spec.reward_varies_only, **overrides)


def make_agent(cfg: ZeusConfig, env: FamilyEnv) -> Agent:
    """Agent sized for the env, with the parameter normalised on the train values."""
    return Agent(cfg, env.obs_dim, env.action_dim,
                 param_normaliser(env.spec.train, log=cfg.param_space == 'log'))


def make_replay(cfg: ZeusConfig, env: FamilyEnv, agent: Agent, seed: int) -> ReplayBuffer:
    """Return the replay buffer sized for the env: the true values one column per parameter."""
    return ReplayBuffer(cfg.replay_capacity, env.obs_dim, env.action_dim, cfg.context_length,
                        agent.row_dim, seed=seed, param_dim=len(env.param_names))


class CsvLog:
    """Append-only CSV whose header only grows: a column first seen late is added, not dropped.

    A resumed run keeps the columns it started with, in their order. A name
    the header lacks (a metric a method returns that an older run did not
    log, a column added to the trainer since) is appended: the file is
    rewritten with it, empty in the rows before.
    """

    def __init__(self, path: Path, columns: Sequence[str]):
        self.path = path
        new = not path.exists() or path.stat().st_size == 0
        self.columns = tuple(columns) if new else self._header()
        self.file = open(path, 'a', newline='')
        if new:
            csv.DictWriter(self.file, self.columns).writeheader()
            self.file.flush()
        self.widen(columns)

    def _header(self) -> tuple[str, ...]:
        with open(self.path, newline='') as existing:
            return tuple(next(csv.reader(existing), ()))

    def widen(self, names: Iterable[str]) -> None:
        """Append the names the header lacks, rewriting the rows written so far."""
        missing = [n for n in dict.fromkeys(names) if n not in self.columns]
        if not missing:
            return
        self.file.close()
        with open(self.path, newline='') as old:
            rows = list(csv.DictReader(old))
        self.columns = (*self.columns, *missing)
        partial = self.path.with_name(self.path.name + '.partial')
        with open(partial, 'w', newline='') as out:
            writer = csv.DictWriter(out, self.columns)
            writer.writeheader()
            writer.writerows(rows)
        os.replace(partial, self.path)   # a reader sees the old file or the new one
        self.file = open(self.path, 'a', newline='')

    def write(self, row: dict) -> None:
        self.widen(row)
        csv.DictWriter(self.file, self.columns).writerow(
            {c: row.get(c, '') for c in self.columns})
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def parse_overrides(items: Iterable[str] | None) -> dict:
    """`key=value` strings -> config overrides typed by the fields (a later key wins).

    ValueError names a malformed item, a key no config dataclass has, a key
    the run's own options set, or a value its field cannot take.
    """
    kinds = config_types()
    out = {}
    for item in items or ():
        key, equals, value = item.partition('=')
        if not equals:
            raise ValueError(f'--set {item!r}: write KEY=VALUE')
        if key in RUN_KEYS:
            raise ValueError(f'--set {key}: set it with --{key}')
        if key not in kinds:
            raise ValueError(f'--set {key}: {unknown_key_message(key)} '
                             '(train --help lists every field)')
        try:
            out[key] = parse_text(kinds[key], value)
        except ValueError as error:
            raise ValueError(f'--set {key}: {error}') from None
    return out


@dataclass(frozen=True)
class RunArgs:
    """What one training run was asked to do; stored in its checkpoint metadata.

    Every field but `overrides` is an option of `train` (`build_parser`);
    `overrides` holds the learning-configuration fields the user gave (its
    options and `--set KEY=VALUE`), which win over every preset.
    """

    out: Path = setting(help_text='Run directory (checkpoint/, logs, tb/).', required=True)
    family: str = setting('walker-walk-v0', 'Environment family (sim_node.families).',
                          choices=sorted(SIM_FAMILIES))
    family_file: str | None = setting(
        None, 'A family file (YAML, docs: "Your robot") to train on; its name replaces --family.')
    method: str = setting('zeus', 'Context method (one module each in zeus_ros/core/methods).',
                          choices=sorted(METHODS))
    profile: str = setting('cpu', "Preset sizes: 'cpu' (2 CPU cores) or 'paper' (Tables 8-9).",
                           choices=PROFILES)
    steps: int = setting(100_000, 'Timesteps to train to (each steps every training task once).')
    seed: int = setting(1, 'Seed of torch, the trainer, the replay and the episodes.')
    overrides: dict = field(default_factory=dict)
    eval_every: int = setting(10_000, 'Evaluate every N timesteps; 0 = never.')
    eval_episodes: int = setting(1, 'Evaluation episodes per parameter value.')
    eval_max_steps: int | None = setting(
        None, 'Cap on the evaluation episode length (None: the full episode).')
    eval_splits: tuple[str, ...] = setting(SPLITS, 'Splits the periodic evaluation runs.',
                                           choices=SPLITS)
    checkpoint_every: int = setting(5000, 'Checkpoint every N timesteps (and at the end).')
    log_every: int = setting(500, 'Write a train_log.csv row every N timesteps.')
    time_limit: float | None = setting(
        None, 'Stop (with a checkpoint) after this many minutes (None: no limit).')
    save_replay: bool = setting(True, 'Save the replay buffer in the checkpoint.')
    resume: bool = setting(False, 'Continue from --out/checkpoint (with the same config).')
    quiet: bool = setting(False, 'No progress bar.')

    @classmethod
    def from_cli(cls, ns: argparse.Namespace) -> 'RunArgs':
        """Type a parsed command line; ValueError names a bad config key or value.

        A config option (`--alpha-psi 0`) wins over `--set alpha_psi=...`, and a
        later `--set` of a key over an earlier one.
        """
        overrides = parse_overrides(ns.set)
        overrides.update({k: getattr(ns, k) for k in config_option_names()
                          if getattr(ns, k) is not None})
        refuse_foreign_keys(ns.method, overrides)
        run = {f.name: getattr(ns, f.name) for f in fields(cls) if f.name != 'overrides'}
        run.update(out=Path(ns.out), eval_splits=tuple(ns.eval_splits))
        return cls(**run, overrides=overrides)

    def to_json_dict(self) -> dict:
        """JSON-ready fields (for the metadata and the records)."""
        out = asdict(self)
        out['out'] = str(self.out)
        out['eval_splits'] = list(self.eval_splits)
        return out


def config_option_names() -> tuple[str, ...]:
    """Every learning-configuration field that is an option of `train` (not a run option)."""
    return (*(k for k in SHARED_KEYS if k not in RUN_KEYS), *setting_owners())


def build_parser() -> argparse.ArgumentParser:
    """Return the command line of `train`, generated from RunArgs and the config dataclasses."""
    p = argparse.ArgumentParser(
        prog='train', description=__doc__.split('\n')[0],
        # The generated usage line names every option (~40 lines): errors would scroll away.
        usage='%(prog)s --out DIR [run options] [--set KEY=VALUE ...] [config options]',
        epilog='Every learning-configuration option is also settable as --set KEY=VALUE '
               '(the field name, e.g. --set alpha_psi=0); an option wins over --set.')
    add_arguments(p.add_argument_group('run'), RunArgs)
    p.add_argument('--set', nargs='*', action='extend', default=[], metavar='KEY=VALUE',
                   help='set any learning-configuration field below by its name, typed by '
                        'the field (repeatable; a later value of a key wins)')
    shared = p.add_argument_group(
        'learning configuration (zeus_ros.core.config.ZeusConfig)',
        'Unset, a field takes its default or the preset of its profile, family or method '
        '(in brackets); a value given here wins over every preset.')
    add_arguments(shared, ZeusConfig, skip=RUN_KEYS, keep_defaults=False, note=preset_note)
    for cls, methods in settings_groups().items():
        group = p.add_argument_group(f'settings of {", ".join(methods)} '
                                     f'({cls.__module__}.{cls.__name__})')
        add_arguments(group, cls, only=set(cls.__dict__['__annotations__']),
                      keep_defaults=False, note=preset_note)
    return p


# Fixed evaluation start states, the same for every run, method and seed.
EVAL_SEED = 10_000


def sampling_span(family: str, span: str, values: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """[lo], [hi] per parameter that `train_sampling` draws from (`train_span`)."""
    if span == 'live':
        ranges = [p.live_range for p in get_sim_family(family).live_params]
        return (np.array([lo for lo, _ in ranges]), np.array([hi for _, hi in ranges]))
    return (np.min(values, axis=0), np.max(values, axis=0))


class Trainer:
    """State of one training run: envs, windows, agent, replay, logs."""

    def __init__(self, args: RunArgs):
        if args.family_file is not None:
            args = replace(args, family=load_family_file(args.family_file).name)
        self.args = args
        self.cfg = cfg = family_config(args.family, args.profile, args.method, **args.overrides)
        torch.set_num_threads(cfg.num_threads)
        torch.manual_seed(args.seed)
        self.rng = np.random.default_rng(args.seed)
        self.out = Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.values = [as_values(v) for v in get_sim_family(args.family).train]
        self.span = sampling_span(args.family, cfg.train_span, self.values)
        self.batch_size = cfg.batch_size_per_task * len(self.values)
        self.envs = [make_env(args.family, v, seed=None, episode_steps=cfg.episode_steps,
                              reward_in_obs=cfg.reward_in_observation) for v in self.values]
        env0 = self.envs[0]
        self.agent = make_agent(cfg, env0)
        self.replay = make_replay(cfg, env0, self.agent, args.seed)
        self.windows = [ContextWindow(cfg.context_length, env0.obs_dim, env0.action_dim)
                        for _ in self.envs]
        self.timestep = self.env_steps = self.episodes = 0
        self.wall_before = 0.0   # training wall time of the runs this one resumes
        self.resumed = self._resume() if args.resume else None
        self.obs = [self._reset_task(i, env) for i, env in enumerate(self.envs)]
        self.ep_returns = np.zeros(len(self.envs))
        self.last_returns = np.full(len(self.envs), np.nan)
        self.logs = TrainingLogs(self.out, self.agent.metric_names())
        self.on_checkpoint = None   # called with the trainer after every checkpoint (sweeps)

    def _resume(self) -> dict:
        resumed = load_training_checkpoint(self.out / 'checkpoint', self.agent, self.replay)
        self.timestep = resumed['timestep']
        self.env_steps = resumed['env_steps']
        self.episodes = resumed['episodes']
        self.wall_before = resumed['metadata'].steps.wall_s or 0.0
        rngs = resumed['rng_states']
        if 'trainer' in rngs:
            restore_numpy_generator(self.rng, rngs['trainer'])
        if 'replay' in rngs:
            restore_numpy_generator(self.replay.rng, rngs['replay'])
        return resumed

    def _episode_seed(self, task: int) -> int:
        return (self.args.seed * 1_000_003 + self.timestep * 101 + task) % (2 ** 31)

    def wall_s(self) -> float:
        """Training wall time so far, across resumes."""
        return self.wall_before + time.monotonic() - self.started

    def checkpoint(self) -> None:
        counters = {'timestep': self.timestep, 'env_steps': self.env_steps,
                    'update_step': self.agent.update_step, 'episodes': self.episodes}
        rngs = {'trainer': numpy_generator_state(self.rng),
                'replay': numpy_generator_state(self.replay.rng)}
        save_checkpoint(self.out / 'checkpoint', self.agent, env_info(self.envs[0]), counters,
                        rngs, self.replay if self.args.save_replay else None,
                        run=self.args.to_json_dict(), wall_s=self.wall_s())
        if self.on_checkpoint is not None:
            self.on_checkpoint(self)

    def collect(self) -> None:
        """One timestep: every training task steps once; transitions go to the replay."""
        cfg = self.cfg
        self._swap_tasks()
        ctx = [w.arrays() for w in self.windows]
        if self.timestep < cfg.init_steps:
            actions = self.rng.uniform(-1.0, 1.0, (len(self.envs), self.envs[0].action_dim))
        else:
            actions = self.agent.act(np.stack(self.obs), np.stack([c[0] for c in ctx]),
                                     np.stack([c[1] for c in ctx]),
                                     [env.param_values for env in self.envs])
        for i, env in enumerate(self.envs):
            self._step_task(i, env, actions[i])

    def _swap_tasks(self) -> None:
        """Move tasks to another training value mid-episode (`train_swap_prob`; window kept)."""
        if self.cfg.train_swap_prob <= 0:
            return   # no draw: runs without swaps keep the random stream they always had
        jumps = self.rng.random(len(self.envs)) < self.cfg.train_swap_prob
        for env, jump in zip(self.envs, jumps, strict=True):
            targets = self._swap_targets(tuple(env.param_values)) if jump else []
            if targets:
                env.apply_prepared(env.prepare_values(targets[self.rng.integers(len(targets))]))

    def _swap_targets(self, current: tuple) -> list[tuple]:
        """List the training values a task at `current` may jump to (`train_swap_direction`)."""
        if self.cfg.train_sampling != 'values':
            return [self._draw_value()]
        others = [v for v in self.values if v != current]
        if self.cfg.train_swap_direction == 'down':
            return [v for v in others if v < current]   # tuple order: by the first parameter
        return others

    def _draw_value(self) -> tuple:
        """Draw a value over the train values' span, per parameter (`train_sampling`)."""
        lo, hi = self.span
        if self.cfg.train_sampling == 'log-range':
            return tuple(float(v) for v in np.exp(self.rng.uniform(np.log(lo), np.log(hi))))
        return tuple(float(v) for v in self.rng.uniform(lo, hi))

    def _reset_task(self, i: int, env: FamilyEnv) -> np.ndarray:
        """Start task i's next episode, at a freshly drawn value when sampling a range."""
        if self.cfg.train_sampling != 'values':
            env.apply_prepared(env.prepare_values(self._draw_value()))
        return env.reset(seed=self._episode_seed(i))

    def _step_task(self, i: int, env: FamilyEnv, action: np.ndarray) -> None:
        res = env.step(action)
        self.env_steps += 1
        w = self.windows[i]
        if res.instability:
            # The env restarted itself; the transition has no true s'.
            w.clear()
            self.obs[i] = res.observation
            self.ep_returns[i] = 0.0
            return
        continues = w.fill > 0
        w.push(self.obs[i], action, res.reward, res.observation)
        # Time-limit truncation is not a terminal: bootstrap through it.
        self.replay.add(self.obs[i], action, res.reward, res.observation, res.terminal, i,
                        env.param_values, continues)
        self.ep_returns[i] += res.reward
        self.obs[i] = res.observation
        if res.terminal or res.truncated:
            self.episodes += 1
            self.logs.episode(self, i)
            self.last_returns[i] = self.ep_returns[i]
            w.clear()
            self.obs[i] = self._reset_task(i, env)
            self.ep_returns[i] = 0.0

    def evaluate(self) -> dict[str, SplitScore]:
        """Mean deterministic return and success rate per split, by the ROS episode's evaluator."""
        threads = torch.get_num_threads()
        model = InferenceModel.from_agent(self.agent, env_info(self.envs[0]))
        spec = get_sim_family(self.args.family)
        results = {}
        try:
            for split in self.args.eval_splits:
                values = spec.split(split)
                if values:
                    rows = evaluate(model, values, self.args.eval_episodes, EVAL_SEED,
                                    self.args.eval_max_steps)
                    results[split] = self.logs.evaluation(self, split, rows)
        finally:
            torch.set_num_threads(threads)   # the evaluator runs on one thread
        return results

    def _update(self) -> None:
        if self.timestep > self.cfg.init_steps:
            metrics = self.agent.update(self.replay.sample(self.batch_size))
            self.logs.accumulate(metrics)

    def _periodic(self, bar: tqdm) -> bool:
        """Log, evaluate and checkpoint when due at this timestep; True = stop now."""
        args = self.args
        if self.timestep % args.log_every == 0:
            self.logs.train_row(self, bar)
        if args.eval_every and self.timestep % args.eval_every == 0:
            evals = self.evaluate()
            tqdm.write(f'[eval t={self.timestep} env_steps={self.env_steps}] '
                       + ' '.join(f'{k}={v}' for k, v in evals.items()))
        if self.timestep % args.checkpoint_every == 0:
            self.checkpoint()
        if args.time_limit and time.monotonic() - self.started > 60 * args.time_limit:
            tqdm.write(f'time limit reached at timestep {self.timestep}')
            return True
        return False

    def run(self) -> dict:
        """Train until `steps` timesteps (or the time limit); checkpoint on any exit."""
        args = self.args
        self.started = time.monotonic()
        start_env_steps = self.env_steps
        self.logs.restart_rate(self)
        bar = tqdm(total=args.steps, initial=min(self.timestep, args.steps),
                   disable=args.quiet, unit='ts', dynamic_ncols=True)
        try:
            while self.timestep < args.steps:
                self.collect()
                self.timestep += 1
                self._update()
                bar.update(1)
                if self._periodic(bar):
                    break
        finally:
            bar.close()
            self.checkpoint()
            self.logs.close()
        return {'timestep': self.timestep, 'env_steps': self.env_steps,
                'session_env_steps': self.env_steps - start_env_steps,
                'elapsed_s': time.monotonic() - self.started, 'wall_s': self.wall_s()}


@dataclass(frozen=True)
class SplitScore:
    """One split's periodic evaluation: mean return over its values, and success rate."""

    mean_return: float
    success_rate: float | None   # None where the task has no success flag

    @classmethod
    def of(cls, rows: list[dict]) -> SplitScore:
        rates = [r['success_rate'] for r in rows if r['success_rate'] is not None]
        return cls(float(np.mean([r['mean_return'] for r in rows])),
                   float(np.mean(rates)) if rates else None)

    def __str__(self) -> str:
        if self.success_rate is None:
            return f'{self.mean_return:.1f}'
        return f'{self.mean_return:.1f} (success {self.success_rate:.2f})'


class TrainingLogs:
    """The run's CSV logs and TensorBoard scalars, open from the trainer's construction."""

    def __init__(self, out: Path, metric_names: tuple[str, ...]):
        from torch.utils.tensorboard import SummaryWriter
        self.writer = SummaryWriter(str(out / 'tb'))
        # A column per metric the agent declares (a run resumed from an older log gains them).
        self.train = CsvLog(out / 'train_log.csv', (*RUN_COLUMNS, *metric_names))
        # `success`: the split's success rate at that value, empty where the task has no flag.
        self.eval = CsvLog(out / 'eval_log.csv', ('timestep', 'env_steps', 'wall_s', 'split',
                                                  'value', 'return', 'success'))
        self.episodes = CsvLog(out / 'episodes.csv',
                               ('timestep', 'env_steps', 'task', 'value', 'return'))
        self.sums: dict[str, float] = {}
        self.counts: dict[str, int] = {}
        self.last_t, self.last_env = time.monotonic(), 0

    def accumulate(self, metrics: dict) -> None:
        for k, v in metrics.items():
            self.sums[k] = self.sums.get(k, 0.0) + float(v)
            self.counts[k] = self.counts.get(k, 0) + 1

    def restart_rate(self, tr: Trainer) -> None:
        self.last_t, self.last_env = time.monotonic(), tr.env_steps

    def train_row(self, tr: Trainer, bar: tqdm) -> None:
        now = time.monotonic()
        row = {k: self.sums[k] / self.counts[k] for k in self.sums}
        row.update(timestep=tr.timestep, env_steps=tr.env_steps, wall_s=round(tr.wall_s(), 2),
                   env_steps_per_s=(tr.env_steps - self.last_env) / max(now - self.last_t, 1e-9))
        for k, v in row.items():
            if k not in ('timestep', 'env_steps'):
                self.writer.add_scalar(f'train/{k}', v, tr.env_steps)
        self.train.write(row)
        finite = np.isfinite(tr.last_returns)
        bar.set_postfix(sps=f'{row["env_steps_per_s"]:.0f}',
                        ret=f'{np.nanmean(tr.last_returns):.0f}' if finite.any() else '-')
        self.last_t, self.last_env = now, tr.env_steps
        self.sums, self.counts = {}, {}

    def episode(self, tr: Trainer, task: int) -> None:
        self.episodes.write({'timestep': tr.timestep, 'env_steps': tr.env_steps, 'task': task,
                             'value': format_task(tr.envs[task].param_values),
                             'return': round(float(tr.ep_returns[task]), 4)})
        self.writer.add_scalar(f'train_return/task{task}', tr.ep_returns[task], tr.env_steps)

    def evaluation(self, tr: Trainer, split: str, rows: list[dict]) -> SplitScore:
        for r in rows:
            success = r['success_rate']
            self.eval.write({'timestep': tr.timestep, 'env_steps': tr.env_steps,
                             'wall_s': round(tr.wall_s(), 2), 'split': split,
                             'value': format_task(r['value']),
                             'return': round(r['mean_return'], 4),
                             'success': '' if success is None else round(success, 4)})
        score = SplitScore.of(rows)
        self.writer.add_scalar(f'eval/{split}_mean_return', score.mean_return, tr.env_steps)
        if score.success_rate is not None:
            self.writer.add_scalar(f'eval/{split}_success_rate', score.success_rate, tr.env_steps)
        return score

    def close(self) -> None:
        self.writer.close()
        for log in (self.train, self.eval, self.episodes):
            log.close()


def _raise_interrupt(signum: int, frame: FrameType | None):  # noqa: ARG001 (a signal handler's)
    raise KeyboardInterrupt(f'signal {signum}')


def main(argv: list[str] | None = None) -> int:
    """Console entry point (`train`)."""
    parser = build_parser()
    try:
        args = RunArgs.from_cli(parser.parse_args(argv))
    except ValueError as error:
        parser.error(str(error))   # one line and the usage, exit status 2
    if args.family_file is not None:
        try:
            args = replace(args, family=load_family_file(args.family_file).name)
        except FamilyFileError as error:
            print(f'train: {error}', file=sys.stderr)   # one line: the file and the field
            return 1
    try:
        family_config(args.family, args.profile, args.method, **args.overrides)
    except ValueError as error:
        parser.error(str(error))   # one line and the usage, exit status 2
    # SIGTERM ends the run like Ctrl-C: the `finally` of Trainer.run checkpoints.
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        trainer = Trainer(args)
    except CheckpointError as error:
        print(f'cannot resume: {error}', file=sys.stderr)
        return 2
    if trainer.resumed:
        print(f'resumed at timestep {trainer.timestep} (replay restored: '
              f'{trainer.resumed["replay_restored"]}, {len(trainer.replay)} transitions)')
    try:
        result = trainer.run()
    except KeyboardInterrupt as stop:
        print(f'interrupted ({stop}); checkpoint saved at timestep {trainer.timestep}')
        return 130
    rate = result['session_env_steps'] / max(result['elapsed_s'], 1e-9)
    print(f'done: timestep {result["timestep"]}, env steps {result["env_steps"]}, '
          f'{result["elapsed_s"]:.0f} s this session ({rate:.0f} env steps/s), '
          f'{result["wall_s"]:.0f} s in all; checkpoint in {args.out / "checkpoint"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
