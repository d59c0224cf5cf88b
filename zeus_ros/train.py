"""Train ZeUS on every training task of a family (Algorithm 1), ROS-free.

    python -m zeus_ros.train --family walker-walk-v0 --steps 50000 --out runs/w0

One TIMESTEP (the unit of ``--steps``, ``--eval-every``, ``--checkpoint-every``)
steps every training task of the family once, in process, then runs one
update; with 8 training tasks that is 8 environment steps. The first
``init_steps`` timesteps (1500, or 10000 for the reward family) act uniformly
at random and do not update. Each task keeps its own `ContextWindow`, cleared
at its episode boundaries; the replay buffer stores, with every transition,
the window before s_t and the one after (see `zeus_ros.core.replay`).

Writes into ``--out``: ``checkpoint/`` (see `zeus_ros.checkpoint`, replaced
atomically every ``--checkpoint-every`` timesteps and at the end),
``train_log.csv`` (averaged update metrics and speed), ``eval_log.csv`` (one
row per split and parameter value), ``episodes.csv`` and TensorBoard scalars
in ``tb/``. ``--resume`` continues from ``--out/checkpoint`` with the same
config (networks, optimisers, counters, RNG states and, if saved, the replay
buffer); environments start fresh episodes.
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import fields
from pathlib import Path
import signal
import sys
import threading
import time

import numpy as np
import torch
from tqdm import tqdm

from sim_node.env import ParamEnv
from sim_node.families import FAMILIES, SPLITS
from zeus_ros.checkpoint import (CheckpointError, load_training_checkpoint,
                                 numpy_generator_state, restore_numpy_generator,
                                 save_checkpoint)
from zeus_ros.core.agent import Agent, param_normaliser
from zeus_ros.core.config import PROFILES, ZeusConfig, make_config
from zeus_ros.core.methods import METHODS
from zeus_ros.core.replay import ReplayBuffer
from zeus_ros.core.window import ContextWindow

TRAIN_COLUMNS = ('timestep', 'env_steps', 'wall_s', 'env_steps_per_s', 'critic_loss', 'q1',
                 'actor_loss', 'alpha_loss', 'alpha', 'entropy', 'dynamics_loss',
                 'dynamics_mse', 'reward_loss', 'context_loss', 'decoder_loss')


def env_info(env: ParamEnv) -> dict:
    """Describe the environment layout for the checkpoint metadata."""
    return {'param_name': env.spec.param_name, 'joint_names': env.layout.joint_names,
            'position_encoding': env.layout.position_encoding,
            'actuator_names': env.actuator_names, 'train_values': env.spec.train,
            'control_timestep': env.control_timestep}


def make_agent(cfg: ZeusConfig, env: ParamEnv) -> Agent:
    """Agent sized for the env, with the parameter normalised on the train values."""
    return Agent(cfg, env.obs_dim, env.action_dim, param_normaliser(env.spec.train))


def evaluate_agent(agent: Agent, family: str, values, episodes: int = 1, seed: int = 0,
                   max_steps: int | None = None) -> dict[float, float]:
    """Mean deterministic return per value; all (value, episode) pairs step in one batch."""
    cfg = agent.config
    steps = max_steps or cfg.episode_steps
    jobs = [(v, e) for v in values for e in range(episodes)]
    if not jobs:
        return {}
    envs = [ParamEnv(family, v, seed=None, episode_steps=steps) for v, _ in jobs]
    # A different start state per job: one seed for every value would make the
    # whole evaluation hinge on a single (possibly unlucky) initial pose.
    obs = [env.reset(seed=10_000 + 1000 * seed + j) for j, env in enumerate(envs)]
    windows = [ContextWindow(cfg.context_length, env.obs_dim, env.action_dim) for env in envs]
    returns = np.zeros(len(jobs))
    active = np.ones(len(jobs), bool)
    for _ in range(steps):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        ctx = [windows[i].arrays() for i in idx]
        actions = agent.act(np.stack([obs[i] for i in idx]), np.stack([c[0] for c in ctx]),
                            np.stack([c[1] for c in ctx]), [jobs[i][0] for i in idx],
                            deterministic=True)
        for j, i in enumerate(idx):
            res = envs[i].step(actions[j])
            returns[i] += res.reward
            windows[i].push(obs[i], actions[j], res.reward, res.observation)
            obs[i] = res.observation
            if res.truncated or res.terminal or res.instability:
                active[i] = False
    out: dict[float, list] = {}
    for (v, _), r in zip(jobs, returns, strict=True):
        out.setdefault(v, []).append(r)
    return {v: float(np.mean(r)) for v, r in out.items()}


class CsvLog:
    """Append-only CSV with a fixed header."""

    def __init__(self, path: Path, columns):
        self.columns = tuple(columns)
        new = not path.exists()
        self.file = open(path, 'a', newline='')
        self.writer = csv.DictWriter(self.file, self.columns, extrasaction='ignore')
        if new:
            self.writer.writeheader()

    def write(self, row: dict) -> None:
        self.writer.writerow({c: row.get(c, '') for c in self.columns})
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def _parse_bool(text: str) -> bool:
    if text.lower() in ('1', 'true', 'yes', 'on'):
        return True
    if text.lower() in ('0', 'false', 'no', 'off'):
        return False
    raise ValueError(f'{text!r} is not a boolean (true/false)')


def parse_overrides(items) -> dict:
    """`key=value` strings -> config overrides typed by the fields' defaults."""
    kinds = {f.name: type(f.default) for f in fields(ZeusConfig)}
    out = {}
    for item in items or ():
        key, _, value = item.partition('=')
        if key not in kinds:
            raise SystemExit(f'unknown config field {key!r} in --set')
        parse = _parse_bool if kinds[key] is bool else kinds[key]
        try:
            out[key] = parse(value)
        except ValueError as error:
            raise SystemExit(f'--set {key}: {error}') from None
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='train', description=__doc__.split('\n')[0])
    p.add_argument('--family', default='walker-walk-v0', choices=sorted(FAMILIES))
    p.add_argument('--steps', type=int, default=100_000,
                   help='timesteps (each steps every training task once)')
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--out', type=Path, required=True, help='run directory')
    p.add_argument('--profile', default='cpu', choices=PROFILES)
    p.add_argument('--method', default='zeus', choices=sorted(METHODS),
                   help='context method (zeus_ros.core.methods)')
    p.add_argument('--alpha-psi', type=float, default=None,
                   help='context-loss weight (default: Table 11); 0 = no-context-loss')
    p.add_argument('--set', nargs='*', default=[], metavar='KEY=VALUE',
                   help='override any ZeusConfig field (see zeus_ros.core.config)')
    p.add_argument('--eval-every', type=int, default=10_000, help='timesteps; 0 = never')
    p.add_argument('--eval-episodes', type=int, default=1, help='episodes per value')
    p.add_argument('--eval-max-steps', type=int, default=None,
                   help='cap on evaluation episode length (default: full episode)')
    p.add_argument('--eval-splits', nargs='*', default=list(SPLITS), choices=SPLITS)
    p.add_argument('--checkpoint-every', type=int, default=5000, help='timesteps')
    p.add_argument('--log-every', type=int, default=500, help='timesteps')
    p.add_argument('--time-limit', type=float, default=None,
                   help='stop (with a checkpoint) after this many minutes')
    p.add_argument('--no-save-replay', action='store_true',
                   help='leave the replay buffer out of the checkpoint')
    p.add_argument('--resume', action='store_true', help='continue from --out/checkpoint')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    return p


class Trainer:
    """State of one training run: envs, windows, agent, replay, logs."""

    def __init__(self, args):
        self.args = args
        overrides = parse_overrides(args.set)
        if args.alpha_psi is not None:
            overrides['alpha_psi'] = args.alpha_psi
        self.cfg = cfg = make_config(args.family, args.profile, args.method, **overrides)
        torch.set_num_threads(cfg.num_threads)
        torch.manual_seed(args.seed)
        self.rng = np.random.default_rng(args.seed)
        self.out = Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        spec = FAMILIES[args.family]
        self.values = spec.train
        self.envs = [ParamEnv(args.family, v, seed=None, episode_steps=cfg.episode_steps)
                     for v in self.values]
        env0 = self.envs[0]
        self.agent = make_agent(cfg, env0)
        self.replay = ReplayBuffer(cfg.replay_capacity, env0.obs_dim, env0.action_dim,
                                   cfg.context_length, self.agent.row_dim, seed=args.seed)
        self.windows = [ContextWindow(cfg.context_length, env0.obs_dim, env0.action_dim)
                        for _ in self.envs]
        self.timestep = self.env_steps = self.episodes = 0
        self.resumed = None
        if args.resume:
            self.resumed = load_training_checkpoint(self.out / 'checkpoint', self.agent,
                                                    self.replay)
            self.timestep = self.resumed['timestep']
            self.env_steps = self.resumed['env_steps']
            self.episodes = self.resumed['episodes']
            if 'trainer' in self.resumed['rng_states']:
                restore_numpy_generator(self.rng, self.resumed['rng_states']['trainer'])
            if 'replay' in self.resumed['rng_states']:
                restore_numpy_generator(self.replay.rng, self.resumed['rng_states']['replay'])
        self.obs = [env.reset(seed=self._episode_seed(i)) for i, env in enumerate(self.envs)]
        self.ep_returns = np.zeros(len(self.envs))
        self.last_returns = np.full(len(self.envs), np.nan)
        self.writer = None

    def _episode_seed(self, task: int) -> int:
        return (self.args.seed * 1_000_003 + self.timestep * 101 + task) % (2 ** 31)

    def checkpoint(self) -> None:
        counters = {'timestep': self.timestep, 'env_steps': self.env_steps,
                    'update_step': self.agent.update_step, 'episodes': self.episodes}
        rngs = {'trainer': numpy_generator_state(self.rng),
                'replay': numpy_generator_state(self.replay.rng)}
        save_checkpoint(self.out / 'checkpoint', self.agent, env_info(self.envs[0]), counters,
                        rngs, None if self.args.no_save_replay else self.replay)

    def collect(self) -> None:
        """One timestep: every training task steps once; transitions go to the replay."""
        cfg = self.cfg
        ctx = [w.arrays() for w in self.windows]
        if self.timestep < cfg.init_steps:
            actions = self.rng.uniform(-1.0, 1.0, (len(self.envs), self.envs[0].action_dim))
        else:
            actions = self.agent.act(np.stack(self.obs), np.stack([c[0] for c in ctx]),
                                     np.stack([c[1] for c in ctx]), self.values)
        for i, env in enumerate(self.envs):
            res = env.step(actions[i])
            self.env_steps += 1
            if res.instability:
                # The env restarted itself; the transition has no true s'.
                self.windows[i].clear()
                self.obs[i] = res.observation
                self.ep_returns[i] = 0.0
                continue
            w = self.windows[i]
            continues = w.fill > 0
            w.push(self.obs[i], actions[i], res.reward, res.observation)
            # Time-limit truncation is not a terminal: bootstrap through it.
            self.replay.add(self.obs[i], actions[i], res.reward, res.observation,
                            res.terminal, i, self.values[i], continues)
            self.ep_returns[i] += res.reward
            self.obs[i] = res.observation
            if res.terminal or res.truncated:
                self.episodes += 1
                self._log_episode(i)
                w.clear()
                self.obs[i] = env.reset(seed=self._episode_seed(i))
                self.ep_returns[i] = 0.0

    def _log_episode(self, task: int) -> None:
        self.episode_log.write({'timestep': self.timestep, 'env_steps': self.env_steps,
                                'task': task, 'value': self.values[task],
                                'return': round(float(self.ep_returns[task]), 4)})
        self.writer.add_scalar(f'train_return/task{task}', self.ep_returns[task],
                               self.env_steps)
        self.last_returns[task] = self.ep_returns[task]

    def evaluate(self) -> dict:
        args = self.args
        results = {}
        spec = FAMILIES[args.family]
        for split in args.eval_splits:
            values = spec.split(split)
            if not values:
                continue
            res = evaluate_agent(self.agent, args.family, values, args.eval_episodes,
                                 seed=args.seed, max_steps=args.eval_max_steps)
            for v, r in res.items():
                self.eval_log.write({'timestep': self.timestep, 'env_steps': self.env_steps,
                                     'split': split, 'value': v, 'return': round(r, 4)})
            mean = float(np.mean(list(res.values())))
            self.writer.add_scalar(f'eval/{split}_mean_return', mean, self.env_steps)
            results[split] = mean
        return results

    def run(self) -> dict:
        from torch.utils.tensorboard import SummaryWriter
        args, cfg = self.args, self.cfg
        self.writer = SummaryWriter(str(self.out / 'tb'))
        self.train_log = CsvLog(self.out / 'train_log.csv', TRAIN_COLUMNS)
        self.eval_log = CsvLog(self.out / 'eval_log.csv',
                               ('timestep', 'env_steps', 'split', 'value', 'return'))
        self.episode_log = CsvLog(self.out / 'episodes.csv',
                                  ('timestep', 'env_steps', 'task', 'value', 'return'))
        start = time.monotonic()
        last_t, last_env = start, self.env_steps
        sums: dict[str, float] = {}
        counts: dict[str, int] = {}
        evals = {}
        bar = tqdm(total=args.steps, initial=min(self.timestep, args.steps),
                   disable=args.quiet, unit='ts', dynamic_ncols=True)
        try:
            while self.timestep < args.steps:
                self.collect()
                self.timestep += 1
                if self.timestep > cfg.init_steps:
                    m = self.agent.update(self.replay.sample(cfg.batch_size), self.timestep)
                    for k, v in m.items():
                        sums[k] = sums.get(k, 0.0) + float(v)
                        counts[k] = counts.get(k, 0) + 1
                bar.update(1)
                if self.timestep % args.log_every == 0:
                    now = time.monotonic()
                    row = {k: sums[k] / counts[k] for k in sums}
                    row.update(timestep=self.timestep, env_steps=self.env_steps,
                               wall_s=round(now - start, 2),
                               env_steps_per_s=(self.env_steps - last_env) / (now - last_t))
                    for k, v in row.items():
                        if k not in ('timestep', 'env_steps'):
                            self.writer.add_scalar(f'train/{k}', v, self.env_steps)
                    self.train_log.write(row)
                    bar.set_postfix(sps=f'{row["env_steps_per_s"]:.0f}',
                                    ret=f'{np.nanmean(self.last_returns):.0f}'
                                    if np.isfinite(self.last_returns).any() else '-')
                    last_t, last_env = now, self.env_steps
                    sums, counts = {}, {}
                if args.eval_every and self.timestep % args.eval_every == 0:
                    evals = self.evaluate()
                    tqdm.write(f'[eval t={self.timestep} env_steps={self.env_steps}] '
                               + ' '.join(f'{k}={v:.1f}' for k, v in evals.items()))
                if self.timestep % args.checkpoint_every == 0:
                    self.checkpoint()
                if args.time_limit and time.monotonic() - start > 60 * args.time_limit:
                    tqdm.write(f'time limit reached at timestep {self.timestep}')
                    break
        finally:
            bar.close()
            self.checkpoint()
            self.writer.close()
            for log in (self.train_log, self.eval_log, self.episode_log):
                log.close()
        elapsed = time.monotonic() - start
        return {'timestep': self.timestep, 'env_steps': self.env_steps,
                'elapsed_s': elapsed, 'eval': evals}


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt(f'signal {signum}')


def main(argv=None) -> int:
    """Console entry point (`train`)."""
    args = build_parser().parse_args(argv)
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
    rate = result['env_steps'] / max(result['elapsed_s'], 1e-9)
    print(f'done: timestep {result["timestep"]}, env steps {result["env_steps"]}, '
          f'{result["elapsed_s"]:.0f} s ({rate:.0f} env steps/s); '
          f'checkpoint in {args.out / "checkpoint"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
