"""A sweep's grid (the sweep file) and where each of its runs lives.

Shared by the sweep runner (`sweep`) and its results (`sweep_results`), which
import it; neither imports the other's module for it.

The sweep file (YAML):

    name: slippery                # the experiment's folder under storage
    storage: runs/sweeps          # relative to the current directory
    families: [walker-walk-slippery]
    methods: [sac, oracle, zeus-id]
    seeds: [1, 2, 3]
    steps: 60000                  # timesteps per run (the fixed budget)
    max_concurrent: 2
    train: {eval_every: 10000, checkpoint_every: 2500, log_every: 1000}
    overrides: {}                 # config fields for every run (as --set), of every method
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
import os
from pathlib import Path
from typing import Iterable

import yaml

from sim_node.families import SIM_FAMILIES
from zeus_ros.core.config import make_config, RUN_KEYS
from zeus_ros.core.methods import METHODS

TRAIN_KEYS = ('eval_every', 'eval_episodes', 'eval_max_steps', 'checkpoint_every',
              'log_every', 'profile')


@dataclass(frozen=True)
class SweepConfig:
    """A grid of training runs and where they live."""

    name: str
    families: tuple[str, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    steps: int
    storage: str = 'runs/sweeps'
    max_concurrent: int = field(default_factory=lambda: os.cpu_count() or 1)
    train: dict = field(default_factory=dict)
    overrides: dict = field(default_factory=dict)

    @classmethod
    def load(cls, path: str | Path) -> 'SweepConfig':
        """Read and check a sweep file; ValueError says what is wrong."""
        raw = yaml.safe_load(Path(path).read_text()) or {}
        unknown = set(raw) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f'unknown sweep keys {sorted(unknown)}')
        for key in ('families', 'methods', 'seeds'):
            raw[key] = tuple(raw.get(key, ()))
        cfg = cls(**raw)
        bad = [f for f in cfg.families if f not in SIM_FAMILIES] + \
            [m for m in cfg.methods if m not in METHODS]
        if bad or not (cfg.families and cfg.methods and cfg.seeds):
            raise ValueError(f'unknown or missing families/methods/seeds: {bad}')
        if set(cfg.train) - set(TRAIN_KEYS):
            raise ValueError(f'train: keys must be among {TRAIN_KEYS}')
        _check_overrides(cfg.overrides, cfg.methods)
        return cfg

    @property
    def root(self) -> Path:
        """The experiment folder (Tune's state and the run directories)."""
        return Path(self.storage).resolve() / self.name

    def trials(self) -> list[dict]:
        """One parameter dict per run, in the order families, methods, seeds."""
        return [{'family': f, 'method': m, 'seed': s}
                for f in self.families for m in self.methods for s in self.seeds]


def _check_overrides(overrides: dict, methods: Iterable[str]) -> None:
    """Refuse a bad override now, not hours into the grid: every method must take each key."""
    run_owned = sorted(set(overrides) & set(RUN_KEYS))
    if run_owned:
        raise ValueError(f"overrides: {run_owned} are set by the sweep's own keys")
    for method in methods:
        try:   # with the method's presets (zeus-no-context-loss's alpha_psi 0)
            make_config('sweep', 'cpu', method, **overrides)
        except (TypeError, ValueError) as error:
            raise ValueError(f'overrides: {error}') from None


def run_dir(cfg: SweepConfig, family: str, method: str, seed: int) -> Path:
    """Where one run trains and checkpoints (stable across restores)."""
    return cfg.root / 'runs' / f'{family}.{method}.s{seed}'
