"""Checkpoints as safetensors + JSON (never pickle / torch.load).

A checkpoint is a directory:

* ``model.safetensors``: what the deployed policy needs: ``phi.*``, ``psi.*``,
  ``actor.*``, ``decoder.*`` (float32).
* ``training_state.safetensors``: everything else needed to resume: target
  networks and critics, T, R, ``log_alpha``, every Adam state tensor
  (``opt.<optimizer>.<param index>.<key>``), the counters
  (``counters`` = [timestep, env_steps, update_step, episodes]), RNG states
  (``rng.torch`` and JSON-encoded numpy generator states ``rng.<name>``, both
  uint8), and the replay buffer's filled arrays (``replay.*``) unless saving
  them was switched off. Environments are NOT restored: a resumed run starts
  new episodes in every task (seeded from the seed and the timestep).
* ``metadata.json``: format version, family and parameter, observation layout
  (joint names and position encodings), action layout (actuator names), k,
  row width, aggregation, parameter normalisation, the full config, step
  counters, git commit, and the size and SHA-256 of both safetensors files:
  a `CheckpointMetadata` (zeus_ros.deploy.metadata, the schema) written by
  `write_metadata` and read by `load_metadata`, the only two that touch the file.

Every load checks the metadata, the file sizes and SHA-256 sums, the tensor
names and shapes against networks rebuilt from the stored config, and,
when asked, the family and observation/action sizes; anything wrong raises
`CheckpointError` with a message saying what.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
import shutil
import subprocess
import time
from typing import Sequence, TYPE_CHECKING

import numpy as np
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
import torch

from zeus_ros.core.config import ZeusConfig
from zeus_ros.deploy.metadata import (ActionLayoutMeta, CheckpointMetadata, CONFIG_LIMITS,
                                      ContextMeta, FamilyFileMeta, FileMeta, FORMAT_VERSION,
                                      LAYERS, LOG_NORMALISATION, MetadataError, NORMALISATION,
                                      ObsLayoutMeta, ParamNormMeta, parse_section, RunMeta,
                                      StepsMeta, WIDTH)

if TYPE_CHECKING:
    from zeus_ros.core.agent import Agent
    from zeus_ros.core.methods import ContextMethod, ParamScale
    from zeus_ros.core.replay import ReplayBuffer

MODEL_FILE = 'model.safetensors'
STATE_FILE = 'training_state.safetensors'
METADATA_FILE = 'metadata.json'
# Config fields that may differ when resuming (they do not change the learned state).
RESUME_FREE_KEYS = frozenset({'num_threads'})


class CheckpointError(Exception):
    """A checkpoint is missing, corrupt, truncated or does not match what is expected."""


class MetadataRefused(CheckpointError, MetadataError):
    """metadata.json breaks its schema or does not fit the tensors; the message names the field."""


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for chunk in iter(lambda: f.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest()


def git_commit(repo: Path | None = None) -> str:
    """HEAD commit of the source tree ('-dirty' if the learning code is modified), or 'unknown'."""
    repo = repo or Path(__file__).resolve().parents[1]
    try:
        out = subprocess.run(['git', '-C', str(repo), 'rev-parse', 'HEAD'],
                             capture_output=True, text=True, timeout=5)
        sha = out.stdout.strip()
        if not sha:
            return 'unknown'
        dirty = subprocess.run(['git', '-C', str(repo), 'status', '--porcelain', '--',
                                'zeus_ros', 'sim_node'], capture_output=True, text=True,
                               timeout=5).stdout.strip()
        return f'{sha}-dirty' if dirty else sha
    except (OSError, subprocess.SubprocessError):
        return 'unknown'


def resolve_dir(path: str | Path) -> Path:
    """Accept a checkpoint directory or a run directory holding `checkpoint/`."""
    path = Path(path)
    if (path / METADATA_FILE).exists():
        return path
    if (path / 'checkpoint' / METADATA_FILE).exists():
        return path / 'checkpoint'
    raise CheckpointError(f'no checkpoint at {path}: {METADATA_FILE} not found '
                          f'(neither in it nor in {path / "checkpoint"})')


def _bytes_tensor(obj: object) -> torch.Tensor:   # any value json.dumps takes
    data = json.dumps(obj).encode()
    return torch.tensor(list(data), dtype=torch.uint8)


def _tensor_bytes(t: torch.Tensor):
    return json.loads(bytes(t.to(torch.uint8).tolist()).decode())


def _prefixed(prefix: str, state: dict) -> dict:
    return {f'{prefix}.{k}': v.detach().contiguous().clone() for k, v in state.items()}


def _optimizer_tensors(name: str, opt: torch.optim.Optimizer) -> dict:
    out = {}
    for idx, st in opt.state_dict()['state'].items():
        for key, value in st.items():
            t = value if torch.is_tensor(value) else torch.tensor(value)
            out[f'opt.{name}.{idx}.{key}'] = t.detach().contiguous().clone()
    return out


def _load_optimizer(name: str, opt: torch.optim.Optimizer, tensors: dict) -> None:
    prefix = f'opt.{name}.'
    state: dict[int, dict] = {}
    for key, value in tensors.items():
        if key.startswith(prefix):
            idx, sub = key[len(prefix):].split('.', 1)
            state.setdefault(int(idx), {})[sub] = value
    sd = opt.state_dict()
    n_params = sum(len(g['params']) for g in sd['param_groups'])
    if any(i >= n_params for i in state):
        raise CheckpointError(f'optimizer {name}: state for more parameters than it has')
    sd['state'] = state
    opt.load_state_dict(sd)


def build_metadata(agent: Agent, env_info: dict, counters: dict, run: dict | None = None,
                   wall_s: float | None = None) -> CheckpointMetadata:
    """Metadata (without the files' hashes) of an agent and its environment.

    `env_info`: the environment's layout (zeus_ros.learning_tools.train.env_info); `run`:
    the training run's arguments (seed included), as JSON; `wall_s`: its
    training wall time so far, across resumes.
    """
    cfg: ZeusConfig = agent.config
    names = tuple(env_info.get('param_names') or (env_info['param_name'],))
    # The run's arguments are the tool's (RunArgs): read through the schema, not trusted.
    run_meta = None if run is None else parse_section(RunMeta, run, 'run.')
    return CheckpointMetadata(
        format_version=FORMAT_VERSION, family=cfg.family,
        # Always the joined names, as older readers expect; the list only for several.
        param_name=', '.join(names), param_names=names if len(names) > 1 else (),
        obs_layout=_obs_layout(agent.obs_dim, env_info),
        action_layout=_action_layout(agent.action_dim, env_info),
        context=ContextMeta(k=cfg.context_length, row_dim=agent.row_dim,
                            aggregation=cfg.aggregation, context_dim=agent.method.context_dim,
                            method=cfg.method,
                            needs_true_param=agent.method.needs_true_param),
        param_normalisation=_normalisation(agent.param, env_info['train_values']),
        control_timestep=env_info.get('control_timestep'),
        config=cfg.to_dict(),
        steps=StepsMeta(**counters, wall_s=None if wall_s is None else round(wall_s, 2)),
        files={}, run=run_meta, seed=None if run_meta is None else run_meta.seed,
        git_commit=git_commit(), created_unix=time.time(),
        family_file=None if 'family_file' not in env_info else
        parse_section(FamilyFileMeta, env_info['family_file'], 'family_file.'))


def _action_layout(action_dim: int, env_info: dict) -> ActionLayoutMeta:
    """Return the actuators, with their control range and gear when the environment gives them."""
    units = env_info.get('actuator_units')   # (low, high, gear), absent for sawyer's deltas
    low, high, gear = (None, None, None) if units is None else \
        (tuple(float(v) for v in values) for values in units)
    return ActionLayoutMeta(action_dim, tuple(env_info['actuator_names']),
                            ctrl_low=low, ctrl_high=high, gear=gear)


def write_metadata(directory: Path, meta: CheckpointMetadata) -> None:
    """Write `meta` as the metadata.json of a checkpoint (or export) directory."""
    (Path(directory) / METADATA_FILE).write_text(meta.to_json())


def save_checkpoint(path: str | Path, agent: Agent, env_info: dict, counters: dict,
                    rng_states: dict | None = None, replay: ReplayBuffer | None = None,
                    run: dict | None = None, wall_s: float | None = None) -> Path:
    """Write a checkpoint directory atomically (temp dir, then rename); return its path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f'.{path.name}.tmp-{os.getpid()}'
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    model = {}
    for name, module in agent.inference_modules().items():
        model.update(_prefixed(name, module.state_dict()))
    _refuse_non_finite(model, 'weights to save')
    save_file(model, str(tmp / MODEL_FILE))
    state = {}
    for name, module in agent.training_modules().items():
        state.update(_prefixed(name, module.state_dict()))
    state['log_alpha'] = agent.log_alpha.detach().clone().reshape(1)
    for name, opt in agent.optimizers().items():
        state.update(_optimizer_tensors(name, opt))
    state['counters'] = torch.tensor([int(counters.get(k, 0)) for k in
                                      ('timestep', 'env_steps', 'update_step', 'episodes')],
                                     dtype=torch.int64)
    state['rng.torch'] = torch.get_rng_state()
    for name, st in (rng_states or {}).items():
        state[f'rng.{name}'] = _bytes_tensor(st)
    if replay is not None:
        for key, arr in replay.state_arrays().items():
            state[key] = torch.from_numpy(arr)
    save_file(state, str(tmp / STATE_FILE))
    meta = build_metadata(agent, env_info, counters, run, wall_s)
    write_metadata(tmp, meta.with_files(
        {f: FileMeta(sha256_file(tmp / f), (tmp / f).stat().st_size)
         for f in (MODEL_FILE, STATE_FILE)}, replay_saved=replay is not None))
    old = path.parent / f'.{path.name}.old-{os.getpid()}'
    if path.exists():
        path.rename(old)
    tmp.rename(path)
    shutil.rmtree(old, ignore_errors=True)
    return path


def load_metadata(path: str | Path, expected_family: str | None = None,
                  obs_dim: int | None = None,
                  action_dim: int | None = None) -> CheckpointMetadata:
    """Read and check metadata.json; raise CheckpointError on any problem."""
    path = resolve_dir(path)
    try:
        raw = json.loads((path / METADATA_FILE).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CheckpointError(f'{path / METADATA_FILE} is unreadable or not valid JSON: '
                              f'{error}') from None
    if not isinstance(raw, dict):
        raise CheckpointError(f'{path / METADATA_FILE} does not hold a JSON object')
    try:
        meta = CheckpointMetadata.parse(raw)
    except MetadataError as error:
        raise MetadataRefused(f'{path / METADATA_FILE}: {error}') from None
    if expected_family is not None and meta.family != expected_family:
        raise CheckpointError(f'checkpoint is for family {meta.family!r}, '
                              f'expected {expected_family!r}')
    for label, want, have in (('observation size', obs_dim, meta.obs_layout.obs_dim),
                              ('action size', action_dim, meta.action_layout.action_dim)):
        if want is not None and int(want) != int(have):
            raise CheckpointError(f'{label} mismatch: checkpoint has {have}, expected {want}')
    return meta


def _obs_layout(obs_dim: int, env_info: dict) -> ObsLayoutMeta:
    """Return the observation section of an environment's layout."""
    velocities = env_info.get('velocity_encoding')
    return ObsLayoutMeta(obs_dim, tuple(env_info['joint_names']),
                         tuple(env_info['position_encoding']),
                         bool(env_info.get('reward_in_observation', False)),
                         None if velocities is None else tuple(velocities))


def _normalisation(param: ParamScale,
                   train_values: Sequence[float | Sequence[float]]) -> ParamNormMeta:
    """Return the normalisation: offset and scale numbers for one parameter, else lists."""
    values = tuple(v if isinstance(v, float | int) else tuple(v) for v in train_values)
    formula = LOG_NORMALISATION if param.log else NORMALISATION
    if param.param_dim == 1:
        return ParamNormMeta(param.offset[0], param.scale[0], values, formula)
    return ParamNormMeta(tuple(param.offset), tuple(param.scale), values, formula)


def _verified_tensors(path: Path, meta: CheckpointMetadata, name: str) -> dict:
    file = path / name
    info = meta.files.get(name)
    if info is None:
        raise MetadataRefused(f'{path / METADATA_FILE}: files.{name}: missing')
    if not file.exists():
        raise CheckpointError(f'{file} is missing')
    size = file.stat().st_size
    # Which of the two is wrong cannot be told: the message names both.
    if size != info.bytes:
        raise MetadataRefused(f'{file} is {size} bytes, metadata says {info.bytes} '
                              f'(files.{name}.bytes; truncated or replaced)')
    digest = sha256_file(file)
    if digest != info.sha256:
        raise MetadataRefused(f'{file} SHA-256 {digest[:12]}... does not match metadata '
                              f'{info.sha256[:12]}... (files.{name}.sha256; corrupt or '
                              'replaced)')
    try:
        return load_file(str(file))
    except (SafetensorError, OSError, ValueError) as error:
        raise CheckpointError(f'{file} is not a valid safetensors file: {error}') from None


def load_state_into(modules: dict, tensors: dict, source: str) -> None:
    """Load `prefix.*` tensors into each named module, strictly, with clear errors."""
    for prefix, module in modules.items():
        own = module.state_dict()
        sub = {k[len(prefix) + 1:]: v for k, v in tensors.items() if k.startswith(prefix + '.')}
        missing = sorted(set(own) - set(sub))
        extra = sorted(set(sub) - set(own))
        if missing or extra:
            raise CheckpointError(f'{source}: {prefix} tensors do not match the network '
                                  f'(missing {missing[:4]}, unexpected {extra[:4]})')
        for key, value in sub.items():
            if tuple(value.shape) != tuple(own[key].shape):
                raise CheckpointError(
                    f'{source}: shape mismatch for {prefix}.{key}: checkpoint '
                    f'{tuple(value.shape)}, network {tuple(own[key].shape)}')
        module.load_state_dict(sub, strict=True)


def _refuse_non_finite(tensors: dict, source: str) -> None:
    """NaN or infinite weights make a policy that cannot act: refuse them by name."""
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise CheckpointError(f'{source}: non-finite values in {bad[:4]}')


def load_model(path: str | Path, expected_family: str | None = None, obs_dim: int | None = None,
               action_dim: int | None = None,
               ) -> tuple[CheckpointMetadata, ContextMethod, dict[str, torch.nn.Module]]:
    """Load (metadata, method, inference modules dict) after every check.

    The networks are built for real only once a skeleton of them (on torch's
    'meta' device: shapes, no memory) has been found to fit the tensors.
    """
    path = resolve_dir(path)
    meta = load_metadata(path, expected_family, obs_dim, action_dim)
    cfg = meta.zeus_config()
    tensors = _verified_tensors(path, meta, MODEL_FILE)
    _refuse_non_finite(tensors, MODEL_FILE)
    with torch.device('meta'):
        skeleton = _policy_networks(meta, cfg)
    problem = _misfit(meta, cfg, skeleton, tensors)
    if problem is not None:
        raise MetadataRefused(f'{path / METADATA_FILE}: {problem}')
    method, modules = _policy_networks(meta, cfg)
    load_state_into(modules, tensors, MODEL_FILE)
    for m in modules.values():
        m.eval()
    return meta, method, modules


def _policy_networks(meta: CheckpointMetadata, cfg: ZeusConfig) -> tuple:
    """Build (method, inference modules) as the metadata and `cfg` describe them."""
    from zeus_ros.core.agent import build_method, build_policy_modules
    from zeus_ros.core.methods import ParamScale
    obs, act = meta.obs_layout.obs_dim, meta.action_layout.action_dim
    norm = meta.param_normalisation
    method = build_method(cfg, obs, act, ParamScale(norm.offsets, norm.scales, norm.log),
                          training=False)
    return method, {**build_policy_modules(cfg, obs, method.context_dim, act),
                    **method.inference_modules()}


def _shapes(modules: dict) -> dict:
    return {f'{prefix}.{k}': tuple(v.shape)
            for prefix, module in modules.items() for k, v in module.state_dict().items()}


def _differing(a: dict, b: dict) -> set:
    return {k for k in a.keys() | b.keys() if a.get(k) != b.get(k)}


def _misfit(meta: CheckpointMetadata, cfg: ZeusConfig, skeleton: tuple,
            tensors: dict) -> str | None:
    """Return why the metadata does not describe the tensors (naming fields), or None."""
    method, modules = skeleton
    if meta.context.context_dim != method.context_dim:
        return (f'context.context_dim: must be {method.context_dim} (method '
                f'{cfg.method!r} with config.context_dim {cfg.context_dim}), '
                f'got {meta.context.context_dim}')
    unknown = [k for k in tensors if k.split('.', 1)[0] not in modules]
    if unknown:
        return f'{MODEL_FILE} has tensors {unknown[:4]} that method {cfg.method!r} does not have'
    want = _shapes(modules)
    have = {k: tuple(v.shape) for k, v in tensors.items()}
    wrong = _differing(want, have)
    if not wrong:
        return None
    example = sorted(wrong)[0]
    return (f'{" or ".join(_suspects(meta, cfg, want, wrong))}: does not match {MODEL_FILE} '
            f'({example} is {have.get(example, "absent")} there, '
            f'{want.get(example, "absent")} by the metadata)')


def _suspects(meta: CheckpointMetadata, cfg: ZeusConfig, want: dict, wrong: set) -> list[str]:
    """Return the config sizes that shape the tensors that do not fit, likeliest first.

    Each size is moved one up and one down in a skeleton: the tensors that
    change are the ones it shapes. The likeliest culprit shapes exactly the
    misfits (a layer count one off even makes them fit).
    """
    scores = {}
    sizes = cfg.to_dict()   # the shared fields and this method's own settings
    for name, value in _moves(sizes):
        try:
            with torch.device('meta'):
                moved = _differing(want, _shapes(_policy_networks(
                    meta, cfg.replace(**{name: value}))[1]))
        except ValueError:
            continue   # a flag this method cannot take flipped: not the culprit
        if moved & wrong:
            score = len(moved & wrong) / len(moved | wrong)
            scores[f'config.{name}'] = max(score, scores.get(f'config.{name}', 0.0))
    return sorted(scores, key=scores.get, reverse=True)[:3] or ['config']


def _moves(sizes: dict) -> list[tuple[str, int | bool]]:
    """List the config moves to try: widths and layer counts one up and one down, flags flipped.

    A flag can shape tensors too: context_reward sets psi's input width.
    """
    moves = []
    for name, limit in CONFIG_LIMITS.items():
        if name not in sizes:
            continue
        if limit in (WIDTH, LAYERS):
            moves += [(name, v) for v in {max(sizes[name] - 1, limit.lo), sizes[name] + 1}]
        elif limit is None and isinstance(sizes[name], bool):
            moves.append((name, not sizes[name]))
    return moves


def load_training_checkpoint(path: str | Path, agent: Agent,
                             replay: ReplayBuffer | None = None) -> dict:
    """Restore an agent (and replay buffer) for resuming; returns counters and RNG states."""
    path = resolve_dir(path)
    meta = load_metadata(path, agent.config.family, agent.obs_dim, agent.action_dim)
    stored = meta.zeus_config().to_dict()
    now = agent.config.to_dict()
    # Keys of one side only: the two configs are of different methods (method differs too).
    diff = {k: (stored.get(k), now.get(k)) for k in sorted(stored.keys() | now.keys())
            if now.get(k) != stored.get(k) and k not in RESUME_FREE_KEYS}
    if diff:
        raise CheckpointError(f'config differs from the checkpoint (stored, now): {diff}')
    model = _verified_tensors(path, meta, MODEL_FILE)
    load_state_into(agent.inference_modules(), model, MODEL_FILE)
    state = _verified_tensors(path, meta, STATE_FILE)
    load_state_into(agent.training_modules(), state, STATE_FILE)
    with torch.no_grad():
        agent.log_alpha.copy_(state['log_alpha'].reshape(()))
    for name, opt in agent.optimizers().items():
        try:
            _load_optimizer(name, opt, state)
        except (ValueError, RuntimeError) as error:
            raise CheckpointError(f'optimizer {name} state does not fit: {error}') from None
    timestep, env_steps, update_step, episodes = (int(v) for v in state['counters'])
    agent.update_step = update_step
    torch.set_rng_state(state['rng.torch'])
    rngs = {k[4:]: _tensor_bytes(v) for k, v in state.items()
            if k.startswith('rng.') and k != 'rng.torch'}
    if replay is not None and 'replay.meta' in state:
        try:
            replay.load_state_arrays({k: v.numpy() for k, v in state.items()
                                      if k.startswith('replay.')})
        except (ValueError, KeyError) as error:
            raise CheckpointError(f'replay buffer does not fit: {error}') from None
    return {'timestep': timestep, 'env_steps': env_steps, 'update_step': update_step,
            'episodes': episodes, 'rng_states': rngs, 'metadata': meta,
            'replay_restored': replay is not None and 'replay.meta' in state}


def numpy_generator_state(gen: np.random.Generator) -> dict:
    """JSON-able state of a numpy Generator (PCG64 ints as strings)."""
    st = gen.bit_generator.state
    return json.loads(json.dumps(st, default=str))


def restore_numpy_generator(gen: np.random.Generator, state: dict) -> None:
    """Inverse of `numpy_generator_state`."""
    st = dict(state)
    st['state'] = {k: int(v) for k, v in st['state'].items()}
    gen.bit_generator.state = st
