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
  counters, git commit, and the size and SHA-256 of both safetensors files.

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

import numpy as np
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
import torch

from zeus_ros.core.config import ZeusConfig
from zeus_ros.deploy.metadata import CheckpointMetadata, MetadataError

FORMAT_VERSION = 1
MODEL_FILE = 'model.safetensors'
STATE_FILE = 'training_state.safetensors'
METADATA_FILE = 'metadata.json'
# Config fields that may differ when resuming (they do not change the learned state).
RESUME_FREE_KEYS = frozenset({'num_threads'})


class CheckpointError(Exception):
    """A checkpoint is missing, corrupt, truncated or does not match what is expected."""


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


def resolve_dir(path) -> Path:
    """Accept a checkpoint directory or a run directory holding `checkpoint/`."""
    path = Path(path)
    if (path / METADATA_FILE).exists():
        return path
    if (path / 'checkpoint' / METADATA_FILE).exists():
        return path / 'checkpoint'
    raise CheckpointError(f'no checkpoint at {path}: {METADATA_FILE} not found '
                          f'(neither in it nor in {path / "checkpoint"})')


def _bytes_tensor(obj) -> torch.Tensor:
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


def build_metadata(agent, env_info: dict, counters: dict, run: dict | None = None,
                   wall_s: float | None = None) -> dict:
    """Metadata dict (without file hashes) for an agent and its environment.

    `run`: the training run's arguments (seed included); `wall_s`: its training
    wall time so far, across resumes.
    """
    cfg: ZeusConfig = agent.config
    return {
        'format_version': FORMAT_VERSION,
        'family': cfg.family,
        **_parameter_names(env_info),
        'obs_layout': {'obs_dim': agent.obs_dim,
                       'joint_names': list(env_info['joint_names']),
                       'position_encoding': list(env_info['position_encoding']),
                       'reward_in_observation': bool(env_info.get('reward_in_observation',
                                                                  False)),
                       **_velocity_encoding(env_info)},
        'action_layout': {'action_dim': agent.action_dim,
                          'actuator_names': list(env_info['actuator_names']),
                          'range': [-1.0, 1.0]},
        'context': {'k': cfg.context_length, 'row_dim': agent.row_dim,
                    'row_layout': 'concat(s, a, [r], s_next) float32',
                    'aggregation': cfg.aggregation,
                    'context_dim': agent.method.context_dim,
                    'method': cfg.method,
                    'needs_true_param': agent.method.needs_true_param,
                    'empty_window': 'zero latent'},
        'param_normalisation': {**_normalisation(agent.param),
                                'formula': '(value - offset) / scale',
                                'train_values': [v if isinstance(v, float | int) else list(v)
                                                 for v in env_info['train_values']]},
        'control_timestep': env_info.get('control_timestep'),
        'config': cfg.to_dict(),
        'steps': dict(counters, **({} if wall_s is None else {'wall_s': round(wall_s, 2)})),
        'run': run,
        'seed': None if run is None else run.get('seed'),
        'git_commit': git_commit(),
        'created_unix': time.time(),
    }


def save_checkpoint(path, agent, env_info: dict, counters: dict, rng_states: dict | None = None,
                    replay=None, run: dict | None = None, wall_s: float | None = None) -> Path:
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
    meta['files'] = {f: {'sha256': sha256_file(tmp / f), 'bytes': (tmp / f).stat().st_size}
                     for f in (MODEL_FILE, STATE_FILE)}
    meta['replay_saved'] = replay is not None
    (tmp / METADATA_FILE).write_text(json.dumps(meta, indent=2, sort_keys=True))
    old = path.parent / f'.{path.name}.old-{os.getpid()}'
    if path.exists():
        path.rename(old)
    tmp.rename(path)
    shutil.rmtree(old, ignore_errors=True)
    return path


def load_metadata(path, expected_family: str | None = None, obs_dim: int | None = None,
                  action_dim: int | None = None) -> dict:
    """Read and check metadata.json; raise CheckpointError on any problem."""
    path = resolve_dir(path)
    try:
        meta = json.loads((path / METADATA_FILE).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CheckpointError(f'{path / METADATA_FILE} is unreadable or not valid JSON: '
                              f'{error}') from None
    if not isinstance(meta, dict):
        raise CheckpointError(f'{path / METADATA_FILE} does not hold a JSON object')
    try:
        typed = CheckpointMetadata.parse(meta)
        typed.zeus_config()
    except MetadataError as error:
        raise CheckpointError(f'{path / METADATA_FILE}: {error}') from None
    if typed.format_version != FORMAT_VERSION:
        raise CheckpointError(f'checkpoint format {typed.format_version}, '
                              f'this code reads {FORMAT_VERSION}')
    if expected_family is not None and typed.family != expected_family:
        raise CheckpointError(f'checkpoint is for family {typed.family!r}, '
                              f'expected {expected_family!r}')
    if typed.config.get('family') != typed.family:
        raise CheckpointError('metadata family and config family disagree')
    for label, want, have in (('observation size', obs_dim, typed.obs_layout.obs_dim),
                              ('action size', action_dim, typed.action_layout.action_dim)):
        if want is not None and int(want) != int(have):
            raise CheckpointError(f'{label} mismatch: checkpoint has {have}, expected {want}')
    return meta


def _parameter_names(env_info: dict) -> dict:
    """param_name (always, as older readers expect) and, for several, param_names."""
    names = tuple(env_info.get('param_names') or (env_info['param_name'],))
    if len(names) == 1:
        return {'param_name': names[0]}
    return {'param_name': ', '.join(names), 'param_names': list(names)}


def _normalisation(param) -> dict:
    """Return offset and scale as metadata.json holds them: numbers for one parameter, lists."""
    if param.param_dim == 1:
        return {'offset': param.offset[0], 'scale': param.scale[0]}
    return {'offset': list(param.offset), 'scale': list(param.scale)}


def _velocity_encoding(env_info: dict) -> dict:
    """Return the layout's velocity encoding, written only when some velocity is dropped."""
    encoding = env_info.get('velocity_encoding')
    return {} if encoding is None else {'velocity_encoding': list(encoding)}


def _verified_tensors(path: Path, meta: dict, name: str) -> dict:
    file = path / name
    info = meta['files'].get(name)
    if info is None:
        raise CheckpointError(f'metadata lists no {name}')
    if not file.exists():
        raise CheckpointError(f'{file} is missing')
    size = file.stat().st_size
    if size != info['bytes']:
        raise CheckpointError(f'{file} is {size} bytes, metadata says {info["bytes"]} '
                              f'(truncated or replaced)')
    digest = sha256_file(file)
    if digest != info['sha256']:
        raise CheckpointError(f'{file} SHA-256 {digest[:12]}... does not match metadata '
                              f'{info["sha256"][:12]}... (corrupt or replaced)')
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


def load_model(path, expected_family: str | None = None, obs_dim: int | None = None,
               action_dim: int | None = None):
    """Load (metadata, method, inference modules dict) after every check."""
    from zeus_ros.core.agent import build_method, build_policy_modules
    from zeus_ros.core.methods import ParamScale
    path = resolve_dir(path)
    meta = load_metadata(path, expected_family, obs_dim, action_dim)
    cfg = ZeusConfig.from_dict(meta['config'])
    obs, act = meta['obs_layout']['obs_dim'], meta['action_layout']['action_dim']
    norm = meta['param_normalisation']
    method = build_method(cfg, obs, act, ParamScale(norm['offset'], norm['scale']),
                          training=False)
    modules = {**build_policy_modules(cfg, obs, method.context_dim, act),
               **method.inference_modules()}
    tensors = _verified_tensors(path, meta, MODEL_FILE)
    unknown = [k for k in tensors if k.split('.', 1)[0] not in modules]
    if unknown:
        raise CheckpointError(f'{MODEL_FILE} has unexpected tensors {unknown[:4]}')
    _refuse_non_finite(tensors, MODEL_FILE)
    load_state_into(modules, tensors, MODEL_FILE)
    for m in modules.values():
        m.eval()
    return meta, method, modules


def load_training_checkpoint(path, agent, replay=None) -> dict:
    """Restore an agent (and replay buffer) for resuming; returns counters and RNG states."""
    path = resolve_dir(path)
    meta = load_metadata(path, agent.config.family, agent.obs_dim, agent.action_dim)
    stored = ZeusConfig.from_dict(meta['config']).to_dict()
    now = agent.config.to_dict()
    diff = {k: (v, now[k]) for k, v in stored.items()
            if now[k] != v and k not in RESUME_FREE_KEYS}
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
