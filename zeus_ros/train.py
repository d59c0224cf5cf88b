"""Train ZeUS on every training task of a family (Algorithm 1), ROS-free.

    python -m zeus_ros.train --family walker-walk-v0 --steps 50000 --out runs/w0

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
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
import signal
import sys
import threading
import time

import numpy as np
import torch
from tqdm import tqdm

from sim_node.env import make_env, ParamEnv
from sim_node.families import (as_values, format_task, get_sim_family, SIM_FAMILIES,
                               SPLITS)
from zeus_ros.deploy.checkpoint import (CheckpointError, load_training_checkpoint,
                                 numpy_generator_state, restore_numpy_generator,
                                 save_checkpoint)
from zeus_ros.core.agent import Agent, param_normaliser
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.core.config import PROFILES, ZeusConfig, make_config
from zeus_ros.core.methods import METHODS
from zeus_ros.core.replay import ReplayBuffer
from zeus_ros.core.window import ContextWindow
from zeus_ros.evaluate import evaluate

TRAIN_COLUMNS = ('timestep', 'env_steps', 'wall_s', 'env_steps_per_s', 'critic_loss', 'q1',
                 'actor_loss', 'alpha_loss', 'alpha', 'entropy', 'dynamics_loss',
                 'dynamics_mse', 'reward_loss', 'context_loss', 'decoder_loss')


def env_info(env: ParamEnv) -> dict:
    """Describe the environment layout for the checkpoint metadata (any family's env)."""
    return {'param_name': ', '.join(env.param_names), 'param_names': env.param_names,
            'joint_names': env.layout.joint_names,
            'position_encoding': env.layout.position_encoding,
            'actuator_names': env.actuator_names, 'train_values': env.spec.train,
            'control_timestep': env.control_timestep,
            'reward_in_observation': env.layout.reward_in_observation,
            'velocity_encoding': env.layout.velocity_encoding}


def family_config(family: str, profile: str = 'cpu', method: str = 'zeus',
                  **overrides) -> ZeusConfig:
    """Build the preset with the family's facts (Table 11's alpha_psi, reward-varying)."""
    spec = get_sim_family(family)
    if hasattr(spec, 'episode_steps'):   # a family with its own horizon (Sawyer: Table 9's 40)
        overrides = {'episode_steps': spec.episode_steps, **overrides}
    return make_config(family, profile, method, family_alpha_psi=spec.alpha_psi,
                       reward_varying=spec.reward_varies_only, **overrides)


def make_agent(cfg: ZeusConfig, env: ParamEnv) -> Agent:
    """Agent sized for the env, with the parameter normalised on the train values."""
    return Agent(cfg, env.obs_dim, env.action_dim, param_normaliser(env.spec.train))


def make_replay(cfg: ZeusConfig, env, agent: Agent, seed: int) -> ReplayBuffer:
    """Return the replay buffer sized for the env: the true values one column per parameter."""
    return ReplayBuffer(cfg.replay_capacity, env.obs_dim, env.action_dim, cfg.context_length,
                        agent.row_dim, seed=seed, param_dim=len(env.param_names))


class CsvLog:
    """Append-only CSV with a fixed header."""

    def __init__(self, path: Path, columns):
        self.columns = tuple(columns)
        new = not path.exists() or path.stat().st_size == 0
        if not new:  # a resumed run keeps the header it started with
            with open(path, newline='') as existing:
                self.columns = tuple(next(csv.reader(existing), self.columns))
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
    """Command-line arguments of `train`; `RunArgs.from_cli` types them."""
    p = argparse.ArgumentParser(prog='train', description=__doc__.split('\n')[0])
    p.add_argument('--family', default='walker-walk-v0', choices=sorted(SIM_FAMILIES))
    p.add_argument('--steps', type=int, default=100_000,
                   help='timesteps (each steps every training task once)')
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--out', type=Path, required=True, help='run directory')
    p.add_argument('--profile', default='cpu', choices=PROFILES)
    p.add_argument('--method', default='zeus', choices=sorted(METHODS),
                   help='context method (zeus_ros.core.methods)')
    p.add_argument('--alpha-psi', type=float, default=None,
                   help='context-loss weight (default: Table 11); 0 = no-context-loss')
    p.add_argument('--set', nargs='*', action='extend', default=[], metavar='KEY=VALUE',
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


@dataclass(frozen=True)
class RunArgs:
    """What one training run was asked to do; stored in its checkpoint metadata."""

    out: Path
    family: str = 'walker-walk-v0'
    method: str = 'zeus'
    profile: str = 'cpu'
    steps: int = 100_000
    seed: int = 1
    overrides: dict = field(default_factory=dict)
    eval_every: int = 10_000
    eval_episodes: int = 1
    eval_max_steps: int | None = None
    eval_splits: tuple = SPLITS
    checkpoint_every: int = 5000
    log_every: int = 500
    time_limit: float | None = None
    save_replay: bool = True
    resume: bool = False
    quiet: bool = False

    @classmethod
    def from_cli(cls, ns: argparse.Namespace) -> 'RunArgs':
        """Type a parsed command line (the config overrides of --set and --alpha-psi)."""
        overrides = parse_overrides(ns.set)
        if ns.alpha_psi is not None:
            overrides['alpha_psi'] = ns.alpha_psi
        return cls(out=Path(ns.out), family=ns.family, method=ns.method, profile=ns.profile,
                   steps=ns.steps, seed=ns.seed, overrides=overrides,
                   eval_every=ns.eval_every, eval_episodes=ns.eval_episodes,
                   eval_max_steps=ns.eval_max_steps, eval_splits=tuple(ns.eval_splits),
                   checkpoint_every=ns.checkpoint_every, log_every=ns.log_every,
                   time_limit=ns.time_limit, save_replay=not ns.no_save_replay,
                   resume=ns.resume, quiet=ns.quiet)

    def to_json_dict(self) -> dict:
        """JSON-ready fields (for the metadata and the records)."""
        out = asdict(self)
        out['out'] = str(self.out)
        out['eval_splits'] = list(self.eval_splits)
        return out


# Fixed evaluation start states, the same for every run, method and seed.
EVAL_SEED = 10_000


class Trainer:
    """State of one training run: envs, windows, agent, replay, logs."""

    def __init__(self, args: RunArgs):
        self.args = args
        self.cfg = cfg = family_config(args.family, args.profile, args.method, **args.overrides)
        torch.set_num_threads(cfg.num_threads)
        torch.manual_seed(args.seed)
        self.rng = np.random.default_rng(args.seed)
        self.out = Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.values = [as_values(v) for v in get_sim_family(args.family).train]
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
        self.obs = [env.reset(seed=self._episode_seed(i)) for i, env in enumerate(self.envs)]
        self.ep_returns = np.zeros(len(self.envs))
        self.last_returns = np.full(len(self.envs), np.nan)
        self.logs = TrainingLogs(self.out)
        self.on_checkpoint = None   # called with the trainer after every checkpoint (sweeps)

    def _resume(self) -> dict:
        resumed = load_training_checkpoint(self.out / 'checkpoint', self.agent, self.replay)
        self.timestep = resumed['timestep']
        self.env_steps = resumed['env_steps']
        self.episodes = resumed['episodes']
        self.wall_before = float(resumed['metadata']['steps'].get('wall_s', 0.0))
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
        others = [v for v in self.values if v != current]
        if self.cfg.train_swap_direction == 'down':
            return [v for v in others if v < current]   # tuple order: by the first parameter
        return others

    def _step_task(self, i: int, env: ParamEnv, action: np.ndarray) -> None:
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
            self.obs[i] = env.reset(seed=self._episode_seed(i))
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
            metrics = self.agent.update(self.replay.sample(self.batch_size), self.timestep)
            self.logs.accumulate(metrics)

    def _periodic(self, bar) -> bool:
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

    def __init__(self, out: Path):
        from torch.utils.tensorboard import SummaryWriter
        self.writer = SummaryWriter(str(out / 'tb'))
        self.train = CsvLog(out / 'train_log.csv', TRAIN_COLUMNS)
        # `success`: the split's success rate at that value, empty where the task has no flag
        # (a run resumed from before this column keeps its old header).
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

    def train_row(self, tr: Trainer, bar) -> None:
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


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt(f'signal {signum}')


def main(argv=None) -> int:
    """Console entry point (`train`)."""
    args = RunArgs.from_cli(build_parser().parse_args(argv))
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
