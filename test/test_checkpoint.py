"""Checkpoints: round trip, resume state, and refusal of corrupt or mismatched ones."""

from dataclasses import replace
import json
import re
import shutil

from conftest import REPO
import numpy as np
import pytest
from safetensors.torch import load_file, save_file
import torch

from sim_node.env import ParamEnv
from zeus_ros.deploy.checkpoint import (CheckpointError, load_metadata, load_training_checkpoint,
                                        MODEL_FILE, save_checkpoint, sha256_file, STATE_FILE,
                                        write_metadata)
from zeus_ros.learning_tools.train import family_config as make_config
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.deploy.metadata import CheckpointMetadata, FileMeta
from zeus_ros.core.replay import ReplayBuffer
from zeus_ros.core.window import ContextWindow
from zeus_ros.learning_tools.train import env_info, make_agent

FAMILY = 'finger-spin-v0'


def tiny(method='zeus', **kw):
    base = dict(hidden_dim=32, context_dim=6, feature_dim=8, encoder_hidden=16,
                context_hidden=16, dynamics_hidden=16, decoder_hidden=8,
                batch_size_per_task=2, replay_capacity=100, num_threads=1)
    base['context_length'] = 5
    base.update(kw)
    return make_config(FAMILY, 'cpu', method, **base)


@pytest.fixture(scope='module')
def env():
    return ParamEnv(FAMILY, seed=0)


def trained_agent(env, cfg=None):
    torch.manual_seed(0)
    agent = make_agent(cfg or tiny(), env)
    replay = ReplayBuffer(agent.config.replay_capacity, env.obs_dim, env.action_dim,
                          agent.config.context_length, agent.row_dim)
    w = ContextWindow(agent.config.context_length, env.obs_dim, env.action_dim)
    obs = env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(40):
        a = rng.uniform(-1, 1, env.action_dim)
        res = env.step(a)
        continues = w.fill > 0
        w.push(obs, a, res.reward, res.observation)
        replay.add(obs, a, res.reward, res.observation, False, 0, 0.05, continues)
        obs = res.observation
    for _ in range(3):
        agent.update(replay.sample(16))
    return agent, replay


def resign(checkpoint, name):
    """Record a replaced file's size and SHA-256 in the metadata (the hash check passes)."""
    meta = load_metadata(checkpoint)
    file = FileMeta(sha256_file(checkpoint / name), (checkpoint / name).stat().st_size)
    write_metadata(checkpoint, replace(meta, files={**meta.files, name: file}))


@pytest.fixture()
def saved(env, tmp_path):
    agent, replay = trained_agent(env)
    path = save_checkpoint(tmp_path / 'ckpt', agent, env_info(env),
                           {'timestep': 7, 'env_steps': 56, 'update_step': 3, 'episodes': 0},
                           {'trainer': {'x': 1}}, replay)
    return agent, replay, path


def test_round_trip_inference_matches_agent(env, saved):
    agent, _, path = saved
    meta = load_metadata(path)
    assert meta.family == FAMILY and meta.context.k == 5
    assert meta.obs_layout.joint_names == tuple(env.joint_names)
    assert meta.action_layout.actuator_names == tuple(env.actuator_names)
    assert meta.files[MODEL_FILE].sha256 == sha256_file(path / MODEL_FILE)
    assert meta.steps.timestep == 7 and meta.replay_saved
    # Written from the typed tree, read back to it: the file is what the tree serialises.
    assert (path / 'metadata.json').read_text() == meta.to_json()
    model = InferenceModel.load(path, expected_family=FAMILY)
    w = ContextWindow(model.k, env.obs_dim, env.action_dim)
    obs = env.reset(seed=3)
    for _ in range(3):
        rows, mask = w.arrays()
        latent = model.context(rows, mask)
        assert latent.dtype == np.float32 and latent.shape == (6,)
        action = model.act(obs, latent)
        expected = agent.act(obs, rows, mask, deterministic=True)
        np.testing.assert_allclose(action, expected, rtol=0, atol=1e-6)
        assert action.dtype == np.float64 and np.all(np.abs(action) <= 1)
        res = env.step(action)
        w.push(obs, action, res.reward, res.observation)
        obs = res.observation
    assert np.isfinite(model.decode(latent))
    empty = model.context(*ContextWindow(model.k, env.obs_dim, env.action_dim).arrays())
    assert not empty.any()


def test_resume_restores_training_state(env, saved):
    agent, replay, path = saved
    torch.manual_seed(123)
    fresh = make_agent(tiny(), env)
    fresh_replay = ReplayBuffer(100, env.obs_dim, env.action_dim, 5, agent.row_dim)
    info = load_training_checkpoint(path, fresh, fresh_replay)
    assert info['timestep'] == 7 and info['update_step'] == 3 == fresh.update_step
    assert info['rng_states']['trainer'] == {'x': 1} and info['replay_restored']
    for name, module in agent.modules().items():
        for p, q in zip(module.state_dict().values(),
                        fresh.modules()[name].state_dict().values(), strict=True):
            assert torch.equal(p, q), name
    assert torch.equal(agent.log_alpha, fresh.log_alpha)
    s1, s2 = agent.critic_opt.state_dict()['state'], fresh.critic_opt.state_dict()['state']
    assert s1.keys() == s2.keys() and len(s1) > 0
    for i in s1:
        assert torch.equal(s1[i]['exp_avg_sq'], s2[i]['exp_avg_sq'])
    assert len(fresh_replay) == len(replay) == 40
    idx = np.arange(40)
    np.testing.assert_array_equal(fresh_replay.windows(idx)[0][0], replay.windows(idx)[0][0])
    # identical next update from identical state
    torch.manual_seed(5)
    b = replay.sample(8)
    torch.manual_seed(6)
    m1 = agent.update(b)
    torch.manual_seed(6)
    m2 = fresh.update(b)
    assert {k: float(v) for k, v in m1.items()} == {k: float(v) for k, v in m2.items()}


def test_resume_refuses_other_config(env, saved):
    _, _, path = saved
    other = make_agent(tiny(alpha_psi=0.0), env)
    with pytest.raises(CheckpointError, match='config differs'):
        load_training_checkpoint(path, other)


def test_corrupt_file_refused(saved):
    _, _, path = saved
    data = bytearray((path / MODEL_FILE).read_bytes())
    data[len(data) // 2] ^= 0xFF
    (path / MODEL_FILE).write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match='SHA-256'):
        InferenceModel.load(path)


def test_truncated_file_refused(saved):
    _, _, path = saved
    data = (path / STATE_FILE).read_bytes()
    (path / STATE_FILE).write_bytes(data[: len(data) // 3])
    with pytest.raises(CheckpointError, match='truncated'):
        load_training_checkpoint(path, saved[0])


def test_missing_file_and_bad_json_refused(saved, tmp_path):
    _, _, path = saved
    copy = tmp_path / 'copy'
    shutil.copytree(path, copy)
    (copy / MODEL_FILE).unlink()
    with pytest.raises(CheckpointError, match='missing'):
        InferenceModel.load(copy)
    (path / 'metadata.json').write_text('{"family": ')
    with pytest.raises(CheckpointError, match='not valid JSON'):
        InferenceModel.load(path)
    with pytest.raises(CheckpointError, match='no checkpoint'):
        InferenceModel.load(tmp_path / 'nowhere')


def test_family_and_size_mismatch_refused(saved):
    _, _, path = saved
    with pytest.raises(CheckpointError, match="family 'finger-spin-v0', expected"):
        InferenceModel.load(path, expected_family='walker-walk-v0')
    with pytest.raises(CheckpointError, match='observation size mismatch'):
        InferenceModel.load(path, obs_dim=18)


def test_shape_mismatch_refused_even_with_matching_hash(saved):
    _, _, path = saved
    tensors = load_file(str(path / MODEL_FILE))
    key = next(k for k in tensors if k.startswith('actor.') and k.endswith('weight'))
    tensors[key] = torch.zeros(tensors[key].shape[0] + 1, tensors[key].shape[1])
    save_file(tensors, str(path / MODEL_FILE))
    resign(path, MODEL_FILE)
    # Refused before the networks are built, naming the sizes that shape the tensor.
    with pytest.raises(CheckpointError, match=rf'config\.hidden_dim.*does not match '
                                              rf'{MODEL_FILE} \({re.escape(key)} is'):
        InferenceModel.load(path)


class _Payload:
    """Unpickling this creates a marker file: proof that a loader executed a pickle."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, 'w'))


@pytest.mark.parametrize('where', [MODEL_FILE, STATE_FILE])
@pytest.mark.parametrize('kind', ['pickle', 'torch.save'])
def test_pickle_payload_in_place_of_weights_is_refused_unexecuted(saved, env, tmp_path,
                                                                  where, kind):
    _, _, path = saved
    bad = tmp_path / 'bad'
    shutil.copytree(path, bad)
    marker = tmp_path / 'executed'
    if kind == 'pickle':
        import pickle
        (bad / where).write_bytes(pickle.dumps(_Payload(marker)))
    else:
        torch.save({'phi.net.0.weight': _Payload(marker)}, bad / where)
    resign(bad, where)
    with pytest.raises(CheckpointError, match='not a valid safetensors'):
        if where == MODEL_FILE:
            InferenceModel.load(bad)
        else:
            load_training_checkpoint(bad, make_agent(tiny(), env))
    assert not marker.exists()


@pytest.mark.parametrize('method', ['sac', 'oracle', 'zeus-id', 'zeus-no-context-loss',
                                    'cadm', 'up-osi', 'hyperdynamics', 'zeus-osi', 'rma'])
def test_every_method_round_trips_and_resumes(env, tmp_path, method):
    # Methods that switch to their own estimate do so from the first update here,
    # so the trainer's acting latent is the deployed one.
    switch = {'rma': {'rma_student_after_updates': 0}, 'up-osi': {'osi_warmup_updates': 0}}
    cfg = tiny(method, **switch.get(method, {}))
    agent, replay = trained_agent(env, cfg)
    path = save_checkpoint(tmp_path / method, agent, env_info(env),
                           {'timestep': 1, 'env_steps': 1, 'update_step': 3, 'episodes': 0},
                           None, replay)
    model = InferenceModel.load(path)
    assert model.method_name == method and model.context_dim == agent.method.context_dim
    rows, mask = ContextWindow(model.k, env.obs_dim, env.action_dim).arrays()
    obs = env.reset(seed=1)
    latent = model.context(rows, mask, true_param=0.05)
    expected = agent.act(obs, rows, mask, [0.05], deterministic=True)
    np.testing.assert_allclose(model.act(obs, latent), expected, atol=1e-6)
    fresh = make_agent(cfg, env)
    load_training_checkpoint(path, fresh, ReplayBuffer(100, env.obs_dim, env.action_dim,
                                                       agent.config.context_length,
                                                       agent.row_dim))
    for name, module in agent.modules().items():
        for p, q in zip(module.state_dict().values(),
                        fresh.modules()[name].state_dict().values(), strict=True):
            assert torch.equal(p, q), name


def test_non_finite_weights_refused(saved, tmp_path):
    _, _, path = saved
    bad = tmp_path / 'nan'
    shutil.copytree(path, bad)
    tensors = load_file(str(bad / MODEL_FILE))
    key = next(k for k in tensors if k.startswith('actor.'))
    tensors[key] = torch.full_like(tensors[key], float('nan'))
    save_file(tensors, str(bad / MODEL_FILE))
    resign(bad, MODEL_FILE)
    with pytest.raises(CheckpointError, match='non-finite'):
        InferenceModel.load(bad)


def _drop(path):
    def edit(meta):
        node = meta
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]
    return edit


def _put(path, value):
    def edit(meta):
        node = meta
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return edit


@pytest.mark.parametrize('edit, field', [
    (_drop(['obs_layout', 'obs_dim']), 'obs_layout.obs_dim: missing'),
    (_drop(['context', 'k']), 'context.k: missing'),
    (_drop(['files', MODEL_FILE, 'sha256']), 'sha256: missing'),
    (_drop(['param_name']), 'param_name: missing'),
    (_drop(['action_layout', 'actuator_names']), 'action_layout.actuator_names: missing'),
    (_put(['context', 'k'], 0), 'context.k: must be in [1, 10000], got 0'),
    (_put(['context', 'k'], 'five'), 'context.k: must be an integer'),
    (_put(['context', 'k'], True), 'context.k: must be an integer'),
    (_put(['config'], []), 'config: must be an object'),
    (_put(['files'], []), 'files: must be an object'),
    (_put(['obs_layout', 'joint_names'], 'rootz'), 'obs_layout.joint_names: must be a list'),
    (_put(['param_normalisation', 'scale'], float('nan')), 'scale: must be a finite number'),
    (_put(['context', 'row_dim'], 3), 'context.row_dim: must be 2'),
    (_put(['action_layout', 'actuator_names'], ['a']),
     'actuator_names: has 1 entries, must have 2'),
    (_put(['config', 'context_length'], 'x'), 'config'),
    (_put(['obs_layout', 'velocity_encoding'], ['raw']), 'velocity_encoding: has 1 entries'),
    (_put(['obs_layout', 'velocity_encoding'], 'raw'), 'velocity_encoding: must be a list'),
])
def test_malformed_metadata_refused_naming_the_field(saved, tmp_path, edit, field):
    _, _, path = saved
    bad = tmp_path / 'bad'
    shutil.copytree(path, bad)
    meta = json.loads((bad / 'metadata.json').read_text())
    edit(meta)
    (bad / 'metadata.json').write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match=re.escape(field)):
        InferenceModel.load(bad)


COMMITTED = sorted(p.parent.relative_to(REPO).as_posix() for folder in ('weights', 'research')
                   for p in (REPO / folder).rglob('metadata.json'))


@pytest.mark.parametrize('folder', COMMITTED)
def test_every_committed_checkpoint_still_loads(folder):
    """Shipped weights and committed run folders hold the flat config of their day."""
    meta = json.loads((REPO / folder / 'metadata.json').read_text())
    assert InferenceModel.load(REPO / folder, expected_family=meta['family']).k >= 1
    parsed = CheckpointMetadata.parse(meta).zeus_config()
    assert parsed.method == meta['config'].get('method', 'zeus')
    assert all(meta['config'][k] == v for k, v in parsed.to_dict().items()
               if k in meta['config'])   # what was written is what is read
