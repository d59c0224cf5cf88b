"""Benchmark the trainer: environment steps per second with updates, and where time goes.

    PYTHONPATH=. python research/benchmarks/bench_trainer.py --family walker-walk-v0 --profile cpu

Runs the real `Trainer.collect` + `ZeusAgent.update` loop (after a short
random-exploration warm-up that fills the replay buffer) and reports env
steps/s counting every training task's step, with the time split into
simulation, acting, bookkeeping (windows + replay), sampling and each update
section (critic, actor+alpha, targets, model/context, decoder).

`--precision bf16` runs the same updates under CPU autocast to bfloat16 (a
lever of issue #13 measured here, not a trainer option: the trainer computes
in float32, and bfloat16's 8-bit mantissa would have to be shown to learn the
same over seeds before it could become one).
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
import tempfile
import time

import torch

from zeus_ros.learning_tools.train import build_parser, RunArgs, Trainer


class _Timed:
    """Wrap a callable and accumulate its wall time."""

    def __init__(self, fn):
        self.fn, self.total = fn, 0.0

    def __call__(self, *args, **kwargs):
        t = time.perf_counter()
        try:
            return self.fn(*args, **kwargs)
        finally:
            self.total += time.perf_counter() - t


def warmed_trainer(family: str, profile: str, warmup: int, threads: int | None,
                   method: str, extra: tuple) -> Trainer:
    """Build a trainer whose replay holds `warmup` timesteps of uniform exploration."""
    out = Path(tempfile.mkdtemp(prefix='zeus_bench_'))
    overrides = [f'init_steps={warmup}', 'replay_capacity=100000', *extra]
    if threads is not None:
        overrides.append(f'num_threads={threads}')
    args = build_parser().parse_args(['--family', family, '--profile', profile,
                                      '--method', method, '--out', str(out),
                                      '--set', *overrides])
    tr = Trainer(RunArgs.from_cli(args))
    while tr.timestep < warmup:  # uniform exploration fills the buffer
        tr.collect()
        tr.timestep += 1
    for _ in range(20):  # warm up torch
        tr.agent.update(tr.replay.sample(tr.batch_size))
    return tr


def instrument(tr: Trainer) -> tuple[list, '_Timed']:
    """Time every environment's step and the agent's act; silence episode logs."""
    sims = [_Timed(env.step) for env in tr.envs]
    for env, timed in zip(tr.envs, sims, strict=True):
        env.step = timed
    act = _Timed(tr.agent.act)
    tr.agent.act = act
    tr.logs.episode = lambda trainer, task: None
    tr.agent.timers = {}
    return sims, act


def update_precision(precision: str):
    """Return the context the updates run in: float32 as trained, or CPU autocast to bf16."""
    if precision == 'bf16':
        return torch.autocast('cpu', dtype=torch.bfloat16)
    return contextlib.nullcontext()


def run(family: str, profile: str, timesteps: int, warmup: int,
        threads: int | None = None, method: str = 'zeus', extra: tuple = (),
        precision: str = 'fp32') -> dict:
    """Measure `timesteps` steady-state timesteps; return the figures.

    `extra`: more `KEY=VALUE` config overrides (e.g. another batch size).
    """
    tr = warmed_trainer(family, profile, warmup, threads, method, extra)
    return measure(tr, timesteps, precision) | {'precision': precision}


def measure(tr: Trainer, timesteps: int, precision: str) -> dict:
    """Time `timesteps` timesteps of collection and one update each on a warmed trainer."""
    sims, act = instrument(tr)
    sample_t = collect_t = 0.0
    env0 = tr.env_steps
    start = time.perf_counter()
    for _ in range(timesteps):
        t0 = time.perf_counter()
        tr.collect()
        t1 = time.perf_counter()
        tr.timestep += 1
        batch = tr.replay.sample(tr.batch_size)
        t2 = time.perf_counter()
        with update_precision(precision):
            tr.agent.update(batch)
        collect_t += t1 - t0
        sample_t += t2 - t1
    total = time.perf_counter() - start
    env_steps = tr.env_steps - env0
    sim = sum(s.total for s in sims)
    split = {'simulation': sim, 'acting': act.total,
             'windows+replay add': collect_t - sim - act.total, 'replay sample': sample_t}
    split.update({f'update/{k}': v for k, v in tr.agent.timers.items()})
    return {'family': tr.cfg.family, 'profile': tr.cfg.profile, 'tasks': len(tr.envs),
            'batch': tr.batch_size, 'hidden': tr.cfg.hidden_dim, 'threads': tr.cfg.num_threads,
            'timesteps': timesteps, 'env_steps': env_steps, 'seconds': total,
            'env_steps_per_s': env_steps / total, 'split': split}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--family', nargs='*', default=['walker-walk-v0'])
    p.add_argument('--profile', default='cpu', choices=('cpu', 'paper'))
    p.add_argument('--timesteps', type=int, default=300)
    p.add_argument('--warmup', type=int, default=200)
    p.add_argument('--method', nargs='*', default=['zeus'], help='context methods to compare')
    p.add_argument('--threads', type=int, nargs='*', default=[None],
                   help="torch threads to compare, one run each (default: the profile's)")
    p.add_argument('--set', nargs='*', default=[], metavar='KEY=VALUE',
                   help='config overrides for every run (as train --set)')
    p.add_argument('--precision', nargs='*', default=['fp32'], choices=('fp32', 'bf16'),
                   help='update precision(s) to compare: fp32 (as trained) or bf16 autocast')
    args = p.parse_args(argv)
    runs = ((f, t, m, x) for f in args.family for t in args.threads for m in args.method
            for x in args.precision)
    for family, threads, method, precision in runs:
        r = run(family, args.profile, args.timesteps, args.warmup, threads, method,
                tuple(args.set), precision)
        print(f"{method} {r['family']} profile={r['profile']} tasks={r['tasks']} "
              f"batch={r['batch']} "
              f"hidden={r['hidden']} threads={r['threads']} precision={precision}: "
              f"{r['env_steps']} env steps in "
              f"{r['seconds']:.1f} s = {r['env_steps_per_s']:.0f} env steps/s (with updates)")
        for k, v in r['split'].items():
            print(f'  {k:<22} {1000 * v / r["timesteps"]:7.2f} ms/timestep '
                  f'({100 * v / r["seconds"]:4.1f} %)')


if __name__ == '__main__':
    main()
