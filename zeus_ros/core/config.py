"""Typed training configuration, with the paper's and a 2-core CPU profile per family.

Every field carries a help string (`setting(default, help)`); the training
command line is generated from them (`zeus_ros.learning_tools.train`) and `describe()` prints
them. Settings only one method reads live in that method's module (its
`MethodSettings` subclass, e.g. `cadm`'s `backward_weight`) and reach the
config as `ZeusConfig.method_settings`; on disk the config is one flat dict
(`to_dict` / `from_dict`), the format every shipped checkpoint holds.
`make_config(family, profile)` returns the preset:

* `paper`: Tables 8-9 and 11 of the appendix (actor/critic hidden 1024, batch
  128 per task, dynamics hidden 512, context length 5, init temperature 0.1,
  critic target / actor update every 2 steps, 1500 (dynamics families) or
  10000 (reward family) uniform-exploration steps, replay capacity 400000).
* `cpu` (default): the same algorithm sized for 2 CPU cores (hidden 256, batch
  32 per task, smaller latents) so that a whole timestep of every training
  task plus one update runs at >= 150 environment steps per second.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, MISSING
import difflib
import json
from typing import Iterable

from zeus_ros.core.methods import METHODS
from zeus_ros.core.methods.base import MethodSettings
from zeus_ros.core.settings import field_types, setting

PROFILES = ('cpu', 'paper')
AGGREGATIONS = ('mean', 'sum', 'max')
TRAIN_SAMPLINGS = ('values', 'range', 'log-range')
TRAIN_SPANS = ('train', 'live')
PARAM_SPACES = ('linear', 'log')
SWAP_DIRECTIONS = ('any', 'down')
# The config fields the run's own options set (--family, --method, --profile).
RUN_KEYS = ('family', 'method', 'profile')


_f = setting


@dataclass(frozen=True)
class ZeusConfig:
    """All hyperparameters of one ZeUS training run."""

    family: str = _f('walker-walk-v0', 'Environment family (sim_node.families).')
    method: str = _f('zeus', 'Context method (zeus_ros.core.methods): zeus, '
                     'zeus-no-context-loss, zeus-id, zeus-osi, sac, oracle, cadm, up-osi, '
                     'hyperdynamics, rma.')
    profile: str = _f('cpu', "Preset the values came from: 'cpu' or 'paper'.")
    # -- context -------------------------------------------------------
    context_length: int = _f(5, 'k: transitions in the context window (Tables 8-9).')
    aggregation: str = _f('mean', 'Permutation-invariant aggregation of psi: mean, sum or max.',
                          choices=AGGREGATIONS)
    context_dim: int = _f(50, 'Size of the latent context psi(H).')
    context_hidden: int = _f(256, 'Hidden width of the per-transition MLP of psi.')
    context_layers: int = _f(2, 'Hidden layers of the per-transition MLP of psi.')
    # -- observation encoder -------------------------------------------
    feature_dim: int = _f(50, 'Size of the latent state phi(s).')
    encoder_hidden: int = _f(256, 'Hidden width of the observation encoder phi.')
    encoder_layers: int = _f(2, 'Hidden layers of phi (MLP; the paper used a 4-layer CNN).')
    # -- SAC -------------------------------------------------------------
    hidden_dim: int = _f(1024, 'Actor/critic hidden width (Tables 8-9).')
    hidden_layers: int = _f(2, 'Actor/critic hidden layers (Tables 8-9).')
    actor_log_std_min: float = _f(-10.0, 'Lower bound of the actor log-std (Tables 8-9).')
    actor_log_std_max: float = _f(2.0, 'Upper bound of the actor log-std (Tables 8-9).')
    discount: float = _f(0.99, 'Discount factor gamma.')
    init_temperature: float = _f(0.1, 'Initial SAC temperature alpha (Tables 8-9).')
    actor_lr: float = _f(3e-4, 'Actor learning rate.')
    critic_lr: float = _f(3e-4, 'Critic (and phi/psi via the critic) learning rate.')
    alpha_lr: float = _f(1e-4, 'Temperature learning rate (SAC-AE default).')
    adam_beta1: float = _f(0.9, 'Adam beta1 for actor, critic and temperature (0.9 / 0.5).')
    critic_tau: float = _f(0.01, 'Polyak rate of the target critic heads (SAC-AE).')
    encoder_tau: float = _f(0.05, 'Polyak rate of the target phi and psi (SAC-AE).')
    actor_update_freq: int = _f(2, 'Actor and temperature update every N updates (Tables 8-9).')
    critic_target_update_freq: int = _f(
        2, "Target networks update every N updates (Tables 8-9 'critic update frequency').")
    # -- ZeUS models -----------------------------------------------------
    alpha_psi: float = _f(1.0, 'Weight of the context loss (Table 11); 0 = no-context-loss.')
    dynamics_hidden: int = _f(512, 'Hidden width of T and R (Tables 8-9).')
    dynamics_layers: int = _f(1, 'Hidden layers of T and R (Tables 8-9).')
    model_lr: float = _f(3e-4, 'Learning rate of psi, T and R in the context/model update.')
    decoder_hidden: int = _f(64, 'Hidden width of the parameter decoder (reads detached psi).')
    decoder_lr: float = _f(1e-3, 'Learning rate of the parameter decoder.')
    # -- data ------------------------------------------------------------
    batch_size_per_task: int = _f(128, 'Batch size per training task (Tables 8-9).')
    replay_capacity: int = _f(400_000, 'Replay buffer capacity in transitions (Tables 8-9).')
    init_steps: int = _f(1500, 'Timesteps of uniform random exploration (1500 / 10000).')
    episode_steps: int = _f(1000, 'Environment steps per episode.')
    train_swap_prob: float = _f(
        0.0, 'Per timestep and training task, the probability that its parameter jumps to '
        'another training value mid-episode, window kept (a live swap in training: windows '
        'that straddle a change, e.g. a target below the running speed). 0 = the paper.')
    train_sampling: str = _f(
        'values', "Which parameter values training visits: 'values' = the family's train "
        "values, one task each (the paper); 'range' = every episode start and every "
        "training swap draws uniformly from [min, max] of the train values, per parameter; "
        "'log-range' = log-uniformly (RMA's wide friction). Tasks keep their slots.",
        choices=TRAIN_SAMPLINGS)
    param_space: str = _f(
        'linear', "How every network that reads or estimates the parameter sees it (the "
        "oracle's input, rma's raw extrinsics, decoders and identification targets): "
        "'linear' = min-max over the train values; 'log' = min-max of their logarithms, "
        'for a positive scale spanning orders of magnitude (friction 0.05-4.5: 0.05 -> 0.1 '
        'then weighs as 2 -> 4).', choices=PARAM_SPACES)
    train_span: str = _f(
        'train', "What 'range' and 'log-range' draw from: 'train' = [min, max] of the train "
        "values; 'live' = the family's live range, every value a running robot may be "
        "swapped to (so no live swap leaves what training saw; the extrapolation split "
        "then lies inside the span and is no longer held out by range).",
        choices=TRAIN_SPANS)
    train_swap_direction: str = _f(
        'any', "Where a training swap goes: 'any' other training value, or 'down' to a "
        "lower one only (none from the lowest): for target velocity, a target below the "
        "speed the robot is running at, the windows where |v - target| reads v - target.",
        choices=SWAP_DIRECTIONS)
    reward_in_observation: bool = _f(
        False, 'Append the reward of the transition into each state to the observation '
        '(appendix B.2.1, for reward-varying families: preset there).')
    num_threads: int = _f(2, 'torch intra-op threads for training.')
    # The method's own settings (its module's `MethodSettings` subclass); None = its defaults.
    method_settings: MethodSettings | None = field(default=None, compare=True)

    def __post_init__(self):
        if self.method_settings is None and self.method in METHODS:
            object.__setattr__(self, 'method_settings', METHODS[self.method].settings_class())

    def validate(self) -> 'ZeusConfig':
        """Raise ValueError on an inconsistent configuration; return self."""
        if self.method not in METHODS:
            raise ValueError(f'method must be one of {sorted(METHODS)}, got {self.method!r}')
        wanted = METHODS[self.method].settings_class
        if type(self.method_settings) is not wanted:
            raise ValueError(f'method_settings must be {wanted.__name__} for method '
                             f'{self.method!r}, got {type(self.method_settings).__name__}')
        self.method_settings.validate()
        for name, allowed in (('profile', PROFILES), ('aggregation', AGGREGATIONS),
                              ('train_sampling', TRAIN_SAMPLINGS),
                              ('train_span', TRAIN_SPANS),
                              ('param_space', PARAM_SPACES),
                              ('train_swap_direction', SWAP_DIRECTIONS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f'{name} must be one of {allowed}, got {getattr(self, name)!r}')
        if self.train_span != 'train' and self.train_sampling == 'values':
            raise ValueError("train_span='live' needs train_sampling 'range' or 'log-range' "
                             "(the listed values have no span to widen)")
        if self.context_length < 1:
            raise ValueError('context_length must be >= 1')
        if self.alpha_psi < 0:
            raise ValueError('alpha_psi must be >= 0')
        if not 0.0 <= self.train_swap_prob <= 1.0:
            raise ValueError('train_swap_prob must be in [0, 1]')
        if self.method == 'zeus-no-context-loss' and self.alpha_psi != 0:
            raise ValueError('zeus-no-context-loss is the alpha_psi = 0 ablation; '
                             f'got alpha_psi {self.alpha_psi}')
        return self

    def to_dict(self) -> dict:
        """Return the flat dict of every shared field and the method's own settings (JSON)."""
        shared = {name: getattr(self, name) for name in SHARED_KEYS}
        return {**shared, **asdict(self.method_settings)}

    @classmethod
    def of(cls, **flat) -> 'ZeusConfig':
        """Build from flat keys: shared fields and the method's own settings (validated).

        A key no dataclass declares, or one of another method's settings, is a
        ValueError that says so.
        """
        method = flat.get('method', _DEFAULTS['method'])
        if method not in METHODS:
            raise ValueError(f'method must be one of {sorted(METHODS)}, got {method!r}')
        refuse_foreign_keys(method, flat)
        own = settings_fields(method)
        settings = METHODS[method].settings_class(**{k: flat[k] for k in own if k in flat})
        return cls(**{k: v for k, v in flat.items() if k not in own},
                   method_settings=settings).validate()

    @classmethod
    def from_dict(cls, data: dict) -> 'ZeusConfig':
        """Build from a checkpoint's flat config; unknown keys are an error.

        Checkpoints written while every method's settings sat in one shared
        config hold all of them: another method's keys are checked (each must
        be a valid value of its field) and left out, since this method never
        read them.
        """
        method = data.get('method', _DEFAULTS['method'])
        if method not in METHODS:
            raise ValueError(f'method must be one of {sorted(METHODS)}, got {method!r}')
        mine = set(SHARED_KEYS) | set(settings_fields(method))
        foreign = {k: v for k, v in data.items() if k not in mine}
        unknown = set(foreign) - set(setting_owners())
        if unknown:
            raise ValueError(f'unknown config keys: {sorted(unknown)}')
        _check_foreign_settings(foreign)
        return cls.of(**{k: v for k, v in data.items() if k in mine})

    def replace(self, **changes) -> 'ZeusConfig':
        """Copy with flat keys changed (validated); a new method starts on its own settings."""
        flat = self.to_dict()
        if changes.get('method', self.method) != self.method:
            flat = {k: v for k, v in flat.items() if k in SHARED_KEYS}
        return ZeusConfig.of(**{**flat, **changes})


SHARED_KEYS = tuple(f.name for f in fields(ZeusConfig) if f.name != 'method_settings')
_DEFAULTS = {f.name: f.default for f in fields(ZeusConfig) if f.default is not MISSING}


def settings_classes() -> dict[type[MethodSettings], tuple[str, ...]]:
    """Return every registered method's settings class and the methods that use it."""
    out: dict[type[MethodSettings], tuple[str, ...]] = {}
    for name, method in METHODS.items():
        out[method.settings_class] = (*out.get(method.settings_class, ()), name)
    return out


def settings_fields(method: str) -> tuple[str, ...]:
    """Return the flat keys of `method`'s own settings."""
    return tuple(f.name for f in fields(METHODS[method].settings_class))


def setting_owners() -> dict[str, tuple[str, ...]]:
    """Return each method-settings key and the methods that read it."""
    owners: dict[str, tuple[str, ...]] = {}
    for name in METHODS:
        for key in settings_fields(name):
            owners[key] = (*owners.get(key, ()), name)
    return owners


def config_types() -> dict[str, type]:
    """Return the value type of every flat config key any method has (shared and settings)."""
    kinds = {k: v for k, v in field_types(ZeusConfig).items() if k in SHARED_KEYS}
    for cls in settings_classes():
        kinds.update(field_types(cls))
    return kinds


def settings_groups() -> dict[type[MethodSettings], tuple[str, ...]]:
    """Return each class that declares method settings and the methods that read its fields."""
    groups: dict[type[MethodSettings], tuple[str, ...]] = {}
    for name, method in METHODS.items():
        for cls in method.settings_class.__mro__:
            if issubclass(cls, MethodSettings) and cls.__dict__.get('__annotations__'):
                groups[cls] = (*groups.get(cls, ()), name)
    return groups


def unknown_key_message(key: str) -> str:
    """Say that `key` is no config field, with the closest field's name if one is close."""
    close = difflib.get_close_matches(key, list(config_types()), 1)
    return f'unknown config field {key!r}' + (f' (did you mean {close[0]!r}?)' if close else '')


def refuse_foreign_keys(method: str, keys: Iterable[str]) -> None:
    """Raise ValueError naming the first key that is neither shared nor `method`'s own."""
    mine = set(SHARED_KEYS) | set(settings_fields(method))
    for key in keys:
        if key in mine:
            continue
        owners = setting_owners().get(key)
        if owners:
            raise ValueError(f'{key} is a setting of method {" / ".join(owners)}; method '
                             f'{method!r} does not read it')
        raise ValueError(unknown_key_message(key))


def _check_foreign_settings(foreign: dict) -> None:
    """Validate other methods' keys with their own settings classes (ValueError if bad)."""
    for cls in settings_classes():
        names = {f.name for f in fields(cls)}
        if names & set(foreign):
            cls(**{k: v for k, v in foreign.items() if k in names}).validate()


PROFILE_PRESETS: dict[str, dict] = {
    'paper': dict(hidden_dim=1024, batch_size_per_task=128, dynamics_hidden=512,
                  replay_capacity=400_000, context_dim=50, feature_dim=50,
                  encoder_hidden=256, context_hidden=256, num_threads=2),
    'cpu': dict(hidden_dim=256, batch_size_per_task=32, dynamics_hidden=256,
                replay_capacity=400_000, context_dim=16, feature_dim=50,
                encoder_hidden=256, context_hidden=128, num_threads=2),
}
# Fields a family's facts preset (make_config's arguments; episode_steps: the trainer's).
FAMILY_PRESETS = {
    'alpha_psi': "the family's Table 11 value",
    'init_steps': '10000 for a reward-varying family',
    'adam_beta1': '0.5 for a reward-varying family',
    'reward_in_observation': 'true for a reward-varying family',
    'episode_steps': "a family's own horizon (Sawyer-Peg: 40)",
}


def make_config(family: str, profile: str = 'cpu', method: str = 'zeus', *,
                family_alpha_psi: float = 1.0, reward_varying: bool = False,
                **overrides) -> ZeusConfig:
    """Preset for a family, profile and method, with optional field overrides.

    The family's facts arrive as arguments (the learning core does not read
    the simulation's tables): `family_alpha_psi` is its Table 11 value, and a
    reward-varying family takes Table 9's exploration and Adam betas and the
    reward in the observation (appendix B.2.1). Then the profile's and the
    method's presets apply, then `overrides` (the user's), which win; any of
    them may name the method's own settings.
    """
    if profile not in PROFILE_PRESETS:
        raise ValueError(f'profile must be one of {PROFILES}, got {profile!r}')
    base = dict(
        family=family, profile=profile, alpha_psi=family_alpha_psi,
        init_steps=10_000 if reward_varying else 1500,
        adam_beta1=0.5 if reward_varying else 0.9, reward_in_observation=reward_varying,
        **PROFILE_PRESETS[profile])
    base['method'] = method
    base.update(METHODS[method].config_defaults if method in METHODS else {})
    base.update(overrides)
    return ZeusConfig.of(**base)


def preset_note(name: str) -> str:
    """Say which presets change field `name` (for its --help line), or ''."""
    parts = [f'{p} {v[name]!r}' for p, v in PROFILE_PRESETS.items() if name in v]
    parts += [f'{m} {cls.config_defaults[name]!r}' for m, cls in METHODS.items()
              if name in cls.config_defaults]
    if name in FAMILY_PRESETS:
        parts.append(FAMILY_PRESETS[name])
    return f'[presets: {"; ".join(parts)}]' if parts else ''


def describe() -> str:
    """One line per flat config key: name, default and help (shared, then the methods')."""
    owners = setting_owners()
    own = {f.name: f for cls in settings_classes() for f in fields(cls)}
    lines = [(f, '') for f in fields(ZeusConfig) if f.name in SHARED_KEYS]
    lines += [(f, f' [{" / ".join(owners[name])}]') for name, f in own.items()]
    return '\n'.join(f'{f.name}{owner} (default {f.default!r}): {f.metadata["help"]}'
                     for f, owner in lines)


def config_json(config: ZeusConfig) -> str:
    """Stable JSON text of a config."""
    return json.dumps(config.to_dict(), sort_keys=True)
