"""Sweeps of training runs (methods x families x seeds) on Ray Tune, resumable.

    python -m zeus_ros.learning_tools.sweep run config/sweeps/slippery.yaml   # local Ray
    python -m zeus_ros.learning_tools.sweep run config/sweeps/slippery.yaml --resume
    python -m zeus_ros.learning_tools.sweep run SWEEP.yaml --address HEAD:6380  # Ray cluster
    python -m zeus_ros.learning_tools.sweep table config/sweeps/slippery.yaml   # table + plots

(`--resume` after a kill; `--address` on a Ray cluster's head.)

One Tune trial is one training run (`zeus_ros.learning_tools.train.Trainer`), one CPU and one
torch thread each, at most `max_concurrent` (default: the machine's cores) at
once. Every trial trains in its own run directory under
``<storage>/<name>/runs/<family>.<method>.s<seed>`` and checkpoints there
every ``checkpoint_every`` timesteps; a trial that starts again (a restored
sweep, or Tune retrying a failure) resumes from that checkpoint, so a killed
sweep loses at most one checkpoint interval per trial. `table` gathers the
final evaluation of every run into ``comparison.csv`` / ``comparison.md``
(mean +- standard error over seeds, per split) and draws learning curves.

The sweep file: `zeus_ros.learning_tools.sweep_config`.
"""

from __future__ import annotations

import argparse
from dataclasses import fields
import os
from pathlib import Path
import sys
from typing import TYPE_CHECKING

import yaml

from zeus_ros.learning_tools.sweep_config import run_dir, SweepConfig

if TYPE_CHECKING:   # ray loads only inside the functions that run a sweep
    from ray import tune


def train_trial(params: dict) -> None:
    """Tune trainable: one training run, resumed from its own checkpoint when it has one."""
    import ray
    from ray import tune
    import torch

    from zeus_ros.learning_tools.train import RunArgs, Trainer
    cfg = SweepConfig(**params['sweep'])
    out = run_dir(cfg, params['family'], params['method'], params['seed'])
    overrides = dict(cfg.overrides, num_threads=1)
    torch.set_num_threads(1)
    args = RunArgs(out=out, family=params['family'], method=params['method'],
                   seed=params['seed'], steps=cfg.steps, overrides=overrides,
                   resume=(out / 'checkpoint' / 'metadata.json').exists(), quiet=True,
                   **cfg.train)
    trainer = Trainer(args)
    node = ray.get_runtime_context().get_node_id()   # which cluster node trained it
    trainer.on_checkpoint = lambda tr: tune.report(
        {'timestep': tr.timestep, 'env_steps': tr.env_steps, 'wall_s': tr.wall_s(), 'node': node})
    trainer.run()


def sweep_trial(params: dict) -> None:
    """Tune's entry point: the grid point's run and the sweep it belongs to."""
    train_trial({**params['trial'], 'sweep': params['sweep']})


def make_tuner(cfg: SweepConfig, resume: bool) -> tune.Tuner:
    """Build a new Tuner over the grid, or restore the interrupted one from `cfg.root`."""
    from ray import tune
    trainable = tune.with_resources(sweep_trial, {'cpu': 1})
    path = cfg.root / 'tune'
    if resume and tune.Tuner.can_restore(str(path)):
        return tune.Tuner.restore(str(path), trainable, resume_unfinished=True,
                                  resume_errored=True)
    sweep = {f.name: getattr(cfg, f.name) for f in fields(cfg)}
    return tune.Tuner(
        trainable, param_space={'sweep': sweep, 'trial': tune.grid_search(cfg.trials())},
        tune_config=tune.TuneConfig(max_concurrent_trials=cfg.max_concurrent),
        run_config=tune.RunConfig(name='tune', storage_path=str(cfg.root),
                                  failure_config=tune.FailureConfig(max_failures=2),
                                  verbose=1))


def start_ray(cfg: SweepConfig, address: str | None) -> None:
    """Local Ray on this machine (loopback, one CPU per trial), or join a cluster."""
    if not address:
        # Before Ray is imported: on Linux it otherwise replaces 127.0.0.1 by the
        # default route's address and listens on every interface; its
        # single-machine mode keeps the node on loopback.
        os.environ['RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER'] = '0'
    import ray
    os.environ.setdefault('RAY_USAGE_STATS_ENABLED', '0')
    repo = str(Path(__file__).resolve().parents[2])   # the folder holding zeus_ros/
    os.environ['PYTHONPATH'] = os.pathsep.join(
        p for p in (repo, os.environ.get('PYTHONPATH')) if p)
    if address:
        ray.init(address=address, runtime_env={'env_vars': {'OMP_NUM_THREADS': '1'}})
        return
    ray.init(num_cpus=cfg.max_concurrent, include_dashboard=False,
             _node_ip_address='127.0.0.1', log_to_driver=False,
             runtime_env={'env_vars': {'OMP_NUM_THREADS': '1', 'PYTHONPATH': repo}})


def run_sweep(cfg: SweepConfig, resume: bool, address: str | None) -> int:
    """Train every grid point (resuming what was interrupted); 0 if all finished."""
    start_ray(cfg, address)
    import ray
    try:
        results = make_tuner(cfg, resume).fit()
    finally:
        ray.shutdown()
    errors = [r.error for r in results if r.error is not None]
    for error in errors:
        print(f'trial failed: {error}', file=sys.stderr)
    return 1 if errors else 0


def main(argv: list[str] | None = None) -> int:
    """Console entry point (`sweep`)."""
    p = argparse.ArgumentParser(prog='sweep', description=__doc__.split('\n')[0])
    sub = p.add_subparsers(dest='command', required=True)
    run = sub.add_parser('run', help='train the grid (Ray Tune)')
    run.add_argument('config', type=Path)
    run.add_argument('--resume', action='store_true', help='restore an interrupted sweep')
    run.add_argument('--address', default=None,
                     help="an existing Ray cluster's head, HOST:PORT (README: on a Ray cluster)")
    table = sub.add_parser('table', help='gather results into a table and plots')
    table.add_argument('config', type=Path)
    table.add_argument('--report', action='store_true',
                       help='also run the adaptation report on every run (slow)')
    args = p.parse_args(argv)
    try:
        cfg = SweepConfig.load(args.config)
    except (OSError, ValueError, TypeError, yaml.YAMLError) as error:
        print(f'bad sweep file {args.config}: {error}', file=sys.stderr)
        return 2
    if args.command == 'run':
        return run_sweep(cfg, args.resume, args.address)
    from zeus_ros.learning_tools.sweep_results import write_results
    print(write_results(cfg, with_report=args.report))
    return 0


if __name__ == '__main__':
    sys.exit(main())
