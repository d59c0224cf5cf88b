"""Typed training configuration, with the paper's and a 2-core CPU profile per family.

Every field carries a help string (`field(metadata={'help': ...})`); `describe()`
prints them. `make_config(family, profile)` returns the preset:

* `paper`: Tables 8-9 and 11 of the appendix (actor/critic hidden 1024, batch
  128 per task, dynamics hidden 512, context length 5, init temperature 0.1,
  critic target / actor update every 2 steps, 1500 (dynamics families) or
  10000 (reward family) uniform-exploration steps, replay capacity 400000).
* `cpu` (default): the same algorithm sized for 2 CPU cores (hidden 256, batch
  32 per task, smaller latents) so that a whole timestep of every training
  task plus one update runs at >= 150 environment steps per second.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
import json

from zeus_ros.core.methods import METHODS

PROFILES = ('cpu', 'paper')
AGGREGATIONS = ('mean', 'sum', 'max')


def _f(default, help_text):
    return field(default=default, metadata={'help': help_text})


@dataclass(frozen=True)
class ZeusConfig:
    """All hyperparameters of one ZeUS training run."""

    family: str = _f('walker-walk-v0', 'Environment family (sim_node.families).')
    method: str = _f('zeus', 'Context method (zeus_ros.core.methods): zeus, '
                     'zeus-no-context-loss, zeus-id, zeus-osi, sac, oracle, cadm, up-osi, '
                     'hyperdynamics.')
    profile: str = _f('cpu', "Preset the values came from: 'cpu' or 'paper'.")
    # -- context -------------------------------------------------------
    context_length: int = _f(5, 'k: transitions in the context window (Tables 8-9).')
    aggregation: str = _f('mean', 'Permutation-invariant aggregation of psi: mean, sum or max.')
    context_dim: int = _f(50, 'Size of the latent context psi(H).')
    context_hidden: int = _f(256, 'Hidden width of the per-transition MLP of psi.')
    context_layers: int = _f(2, 'Hidden layers of the per-transition MLP of psi.')
    context_input: str = _f(
        'transition', "What psi reads per row (zeus-id): 'transition' = concat(s, a, r, s'), "
        "'delta' = concat(s, a, r, s' - s); both standardised by running statistics.")
    context_encoder: str = _f(
        'deepset', "psi of the learned-encoder methods (zeus-id, cadm, up-osi, hyperdynamics): "
        "'deepset' = pooled per-row codes; 'relational' = each row also reads its deviation "
        'from the window mean (codes can depend on how transitions co-vary).')
    context_critic_grad: bool = _f(
        True, 'zeus-id: let the critic TD loss train psi (zeus always does).')
    metric_normalise: bool = _f(
        False, 'zeus-id: divide the task metric and latent distances by their batch means.')
    id_weight: float = _f(
        0.0, 'Weight of the parameter-regression loss THROUGH psi (privileged supervision in '
        'training, as UP-OSI; 0 = the decoder reads a detached latent, a pure probe).')
    backward_weight: float = _f(0.5, 'cadm: weight beta of the backward dynamics loss (Table 10).')
    osi_warmup_updates: int = _f(
        800, 'up-osi: updates that collect with the true parameter before OSI acts '
        '(the paper: 3-5 of 500 iterations; 4/500 of 100k updates).')
    hyper_model_hidden: int = _f(
        64, 'hyperdynamics: hidden width of the generated dynamics model.')
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
    dynamics_loss: str = _f(
        'nll', "'nll': Gaussian NLL (trains mean and log-std); 'mse': mean only.")
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
    train_swap_direction: str = _f(
        'any', "Where a training swap goes: 'any' other training value, or 'down' to a "
        "lower one only (none from the lowest): for target velocity, a target below the "
        "speed the robot is running at, the windows where |v - target| reads v - target.")
    reward_in_observation: bool = _f(
        False, 'Append the reward of the transition into each state to the observation '
        '(appendix B.2.1, for reward-varying families: preset there).')
    num_threads: int = _f(2, 'torch intra-op threads for training.')

    def validate(self) -> 'ZeusConfig':
        """Raise ValueError on an inconsistent configuration; return self."""
        if self.method not in METHODS:
            raise ValueError(f'method must be one of {sorted(METHODS)}, got {self.method!r}')
        if self.context_input not in ('transition', 'delta'):
            raise ValueError("context_input must be 'transition' or 'delta'")
        if self.context_encoder not in ('deepset', 'relational'):
            raise ValueError("context_encoder must be 'deepset' or 'relational'")
        if self.profile not in PROFILES:
            raise ValueError(f'profile must be one of {PROFILES}, got {self.profile!r}')
        if self.aggregation not in AGGREGATIONS:
            raise ValueError(f'aggregation must be one of {AGGREGATIONS}')
        if self.dynamics_loss not in ('nll', 'mse'):
            raise ValueError("dynamics_loss must be 'nll' or 'mse'")
        if self.context_length < 1:
            raise ValueError('context_length must be >= 1')
        if self.alpha_psi < 0:
            raise ValueError('alpha_psi must be >= 0')
        if self.id_weight < 0:
            raise ValueError('id_weight must be >= 0')
        if not 0.0 <= self.train_swap_prob <= 1.0:
            raise ValueError('train_swap_prob must be in [0, 1]')
        if self.train_swap_direction not in ('any', 'down'):
            raise ValueError("train_swap_direction must be 'any' or 'down'")
        if self.method == 'zeus-no-context-loss' and self.alpha_psi != 0:
            raise ValueError('zeus-no-context-loss is the alpha_psi = 0 ablation; '
                             f'got alpha_psi {self.alpha_psi}')
        return self

    def to_dict(self) -> dict:
        """Plain dict of every field (JSON-serialisable)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> 'ZeusConfig':
        """Build from `to_dict()` output; unknown keys are an error."""
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f'unknown config keys: {sorted(unknown)}')
        return cls(**data).validate()

    def replace(self, **changes) -> 'ZeusConfig':
        """Copy with some fields changed (validated)."""
        return replace(self, **changes).validate()


def make_config(family: str, profile: str = 'cpu', method: str = 'zeus', *,
                family_alpha_psi: float = 1.0, reward_varying: bool = False,
                **overrides) -> ZeusConfig:
    """Preset for a family, profile and method, with optional field overrides.

    The family's facts arrive as arguments (the learning core does not read
    the simulation's tables): `family_alpha_psi` is its Table 11 value, and a
    reward-varying family takes Table 9's exploration and Adam betas and the
    reward in the observation (appendix B.2.1). Then
    the method's presets apply, then `overrides` (the user's), which win.
    """
    base = dict(
        family=family, profile=profile, alpha_psi=family_alpha_psi,
        init_steps=10_000 if reward_varying else 1500,
        adam_beta1=0.5 if reward_varying else 0.9, reward_in_observation=reward_varying)
    if profile == 'paper':
        base.update(hidden_dim=1024, batch_size_per_task=128, dynamics_hidden=512,
                    replay_capacity=400_000, context_dim=50, feature_dim=50,
                    encoder_hidden=256, context_hidden=256, num_threads=2)
    elif profile == 'cpu':
        base.update(hidden_dim=256, batch_size_per_task=32, dynamics_hidden=256,
                    replay_capacity=400_000, context_dim=16, feature_dim=50,
                    encoder_hidden=256, context_hidden=128, num_threads=2)
    else:
        raise ValueError(f'profile must be one of {PROFILES}, got {profile!r}')
    base['method'] = method
    base.update(METHODS[method].config_defaults if method in METHODS else {})
    base.update(overrides)
    return ZeusConfig(**base).validate()


def describe() -> str:
    """One line per field: name, default and help."""
    return '\n'.join(f'{f.name} (default {f.default!r}): {f.metadata["help"]}'
                     for f in fields(ZeusConfig))


def config_json(config: ZeusConfig) -> str:
    """Stable JSON text of a config."""
    return json.dumps(config.to_dict(), sort_keys=True)
