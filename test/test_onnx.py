"""ONNX export and the onnx backend: torch's outputs within 1e-5, and the loop it controls."""

import json
import shutil
import subprocess
import sys

from conftest import built_once, REPO
import numpy as np
import pytest
from sim_driver import (assert_same_rewards, collect, episode_rewards, FAMILY,
                        LockstepDriver, start_node, WALKER_WEIGHTS)
from zeus_msgs.msg import StepInfo
from zeus_ros.core.methods import METHODS
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.deploy.backends import load_deployed
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.deploy.onnx_export import export_onnx, MANIFEST
from zeus_ros.deploy.onnx_model import OnnxInferenceModel
from zeus_ros.learning_tools.evaluate import run_episode
from zeus_ros.learning_tools.export_onnx import record_inputs

TOLERANCE = 1e-5
# Shipped weights of five methods, three families (one with two parameters and
# the reward in the observation), latents of 0, 1 and 16 values.
SHIPPED = ['walker-walk-v0-zeus', 'walker-walk-v0-no-context-loss', 'cheetah-run-v1-sac',
           'cheetah-run-v1-up-osi', 'cheetah-run-v1-zeus-id', 'sawyer-peg-v0-zeus']
SHIPPED_METHODS = {'zeus', 'zeus-no-context-loss', 'sac', 'up-osi', 'zeus-id'}
# Every registered method no shipped weights use (a new one is tested when it
# registers), and the encoder options the shipped weights do not use.
TINY = {**{name: (name, []) for name in sorted(set(METHODS) - SHIPPED_METHODS)},
        'zeus-id-max-relational': ('zeus-id', ['aggregation=max',
                                               'context_encoder=relational']),
        'zeus-sum': ('zeus', ['aggregation=sum'])}


def assert_backends_agree(torch_model, onnx_model, steps: int = 150) -> None:
    """Every output of both backends within TOLERANCE on the windows of a real episode."""
    inputs = record_inputs(torch_model, steps)
    # The episode's windows go from empty to full.
    assert not inputs.masks[0].any() and inputs.masks[-1].all()
    close = dict(rtol=0.0, atol=TOLERANCE)
    for t, (rows, mask, obs, param) in enumerate(zip(
            inputs.rows, inputs.masks, inputs.observations, inputs.true_params, strict=True)):
        param = param if torch_model.needs_true_param else None
        latent = torch_model.context(rows, mask, param)
        np.testing.assert_allclose(onnx_model.context(rows, mask, param), latent,
                                   err_msg=f'latent, step {t}', **close)
        np.testing.assert_allclose(onnx_model.features(obs), torch_model.features(obs),
                                   err_msg=f'phi(s), step {t}', **close)
        np.testing.assert_allclose(onnx_model.act(obs, latent), torch_model.act(obs, latent),
                                   err_msg=f'action, step {t}', **close)
        np.testing.assert_allclose(onnx_model.decode_values(latent),
                                   torch_model.decode_values(latent),
                                   err_msg=f'estimates, step {t}', **close)


@pytest.mark.parametrize('name', SHIPPED)
def test_onnx_outputs_equal_torchs_on_a_recorded_episode(tmp_path, name):
    weights = REPO / 'weights' / name
    torch_model = InferenceModel.load(weights)
    assert torch_model.method_name in SHIPPED_METHODS
    onnx_model = OnnxInferenceModel.load(export_onnx(weights, tmp_path / 'onnx'))
    assert onnx_model.context_dim == torch_model.context_dim
    assert ('context' in onnx_model.sessions) == (torch_model.context_dim > 0)
    assert_backends_agree(torch_model, onnx_model)


@pytest.fixture(scope='module')
def tiny_checkpoint(tmp_path_factory):
    """Train a tiny walker checkpoint of a TINY entry a few real steps, once each."""
    made = {}

    def get(name):
        if name not in made:
            method, settings = TINY[name]

            def build(directory):
                out = directory / 'run'
                subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.train',
                                '--family', FAMILY,
                                '--method', method, '--steps', '120', '--out', str(out),
                                '--eval-every', '0', '--checkpoint-every', '120', '--quiet',
                                '--set', 'init_steps=100', 'hidden_dim=32', 'num_threads=1',
                                'batch_size_per_task=4', 'replay_capacity=2000', *settings],
                               check=True, cwd=REPO, capture_output=True)
                return out / 'checkpoint'
            made[name] = built_once(tmp_path_factory, f'onnx-{name}', build)
        return made[name]
    return get


@pytest.mark.parametrize('name', sorted(TINY))
@pytest.mark.ros   # starts processes (the trainer, the export or bench command): not a unit test
def test_every_method_and_encoder_exports(tmp_path, tiny_checkpoint, name):
    weights = tiny_checkpoint(name)
    torch_model = InferenceModel.load(weights)
    onnx_model = OnnxInferenceModel.load(export_onnx(weights, tmp_path / 'onnx'))
    assert_backends_agree(torch_model, onnx_model, steps=60)
    if name == 'oracle':
        # The privileged context reads the true parameter and nothing else.
        assert onnx_model.inputs['context'] == ['true_param']
        with pytest.raises(ValueError, match='needs the true parameter'):
            onnx_model.context(np.zeros((onnx_model.k, onnx_model.row_dim)),
                               np.zeros(onnx_model.k, bool))


def test_the_json_names_every_graphs_inputs_and_outputs_and_the_batch_axis_is_free(tmp_path):
    out = export_onnx(WALKER_WEIGHTS, tmp_path / 'onnx')
    manifest = json.loads((out / MANIFEST).read_text())
    model = InferenceModel.load(WALKER_WEIGHTS)
    graphs = manifest['graphs']
    assert sorted(graphs) == ['actor', 'context', 'decoder', 'phi']
    assert graphs['context']['inputs'] == [
        {'name': 'rows', 'dtype': 'float32', 'shape': ['batch', model.k, model.row_dim]},
        {'name': 'mask', 'dtype': 'bool', 'shape': ['batch', model.k]}]
    assert graphs['actor']['outputs'] == [
        {'name': 'action', 'dtype': 'float32', 'shape': ['batch', model.action_dim]}]
    assert manifest['metadata'] == model.meta.to_dict()
    assert manifest['metadata'] == json.loads((WALKER_WEIGHTS / 'metadata.json').read_text())
    assert manifest['source']['model_sha256'] == model.meta.files['model.safetensors'].sha256
    # The export's copy of metadata.json is the checkpoint's, byte for byte.
    assert (out / 'metadata.json').read_bytes() == (WALKER_WEIGHTS / 'metadata.json').read_bytes()
    # A C++ controller may run a batch: the windows of an episode at once.
    inputs = record_inputs(model, 40)
    onnx_model = OnnxInferenceModel.load(out)
    batch = onnx_model.sessions['context'].run(None, {'rows': inputs.rows,
                                                      'mask': inputs.masks})[0]
    single = np.array([model.context(r, m) for r, m in zip(inputs.rows, inputs.masks,
                                                           strict=True)])
    np.testing.assert_allclose(batch, single, rtol=0.0, atol=TOLERANCE)


def copy_checkpoint(tmp_path):
    weights = tmp_path / 'ckpt'
    shutil.copytree(WALKER_WEIGHTS, weights)
    return weights


def test_a_checkpoint_without_an_export_is_exported_once_into_the_cache(tmp_path,
                                                                         monkeypatch):
    monkeypatch.setenv('ZEUS_ONNX_CACHE', str(tmp_path / 'cache'))
    weights = copy_checkpoint(tmp_path)
    first = OnnxInferenceModel.load(weights)
    assert first.export_dir.parent == tmp_path / 'cache'
    stamp = (first.export_dir / MANIFEST).stat().st_mtime_ns
    again = load_deployed(weights, 'onnx')
    assert again.export_dir == first.export_dir
    assert (again.export_dir / MANIFEST).stat().st_mtime_ns == stamp, 'exported twice'
    # An export beside the weights is used where there is one ...
    own = export_onnx(weights)
    assert own == weights / 'onnx'
    assert OnnxInferenceModel.load(weights).export_dir == own
    # ... unless it is of other weights (a stale export): then the cache's.
    manifest = json.loads((own / MANIFEST).read_text())
    manifest['source']['model_sha256'] = '0' * 64
    (own / MANIFEST).write_text(json.dumps(manifest))
    assert OnnxInferenceModel.load(weights).export_dir == first.export_dir


def test_a_cache_that_cannot_be_written_is_one_clear_error(tmp_path, monkeypatch):
    (tmp_path / 'file').write_text('')
    monkeypatch.setenv('ZEUS_ONNX_CACHE', str(tmp_path / 'file' / 'cache'))
    with pytest.raises(CheckpointError, match='has no ONNX export and none can be written'):
        OnnxInferenceModel.load(copy_checkpoint(tmp_path))


def test_a_corrupt_graph_is_refused(tmp_path):
    out = export_onnx(WALKER_WEIGHTS, tmp_path / 'onnx')
    data = bytearray((out / 'actor.onnx').read_bytes())
    data[-100] ^= 0xFF
    (out / 'actor.onnx').write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match='actor.onnx does not match its size and SHA-256'):
        OnnxInferenceModel.load(out)
    (out / 'actor.onnx').unlink()
    with pytest.raises(CheckpointError, match='actor.onnx is missing'):
        OnnxInferenceModel.load(out)


@pytest.mark.ros   # starts processes (the trainer, the export or bench command): not a unit test
def test_the_export_command_writes_and_checks_an_export(tmp_path):
    out = tmp_path / 'export'
    done = subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.export_onnx',
                           '--weights',
                           str(WALKER_WEIGHTS), '--out', str(out), '--check-steps', '30'],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert 'largest |onnx - torch| over 30 recorded steps' in done.stdout
    assert sorted(p.name for p in out.iterdir()) == [
        'actor.onnx', 'context.onnx', 'decoder.onnx', 'metadata.json', 'onnx.json', 'phi.onnx']
    missing = subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.export_onnx',
                              '--weights',
                              str(tmp_path / 'none')], cwd=REPO, capture_output=True,
                             text=True, timeout=300)
    assert missing.returncode == 1
    assert missing.stderr.strip().startswith('export_onnx: no checkpoint at')


def test_an_unknown_backend_stops_the_node_with_one_line(spawn):
    proc = start_node(spawn, 'policy_node', {'weights': str(WALKER_WEIGHTS),
                                             'backend': 'tensorrt'})
    assert proc.proc.wait(60) == 1
    assert "parameter backend: must be one of torch, onnx, got 'tensorrt'" in proc.output()
    assert 'Traceback' not in proc.output()


def test_onnx_controllers_run_the_in_process_onnx_episode(spawn, ros_node, tmp_path,
                                                         monkeypatch):
    """Both nodes with backend:=onnx (exported on the fly, at once) control the sim."""
    monkeypatch.setenv('ZEUS_ONNX_CACHE', str(tmp_path / 'cache'))
    weights, seed, friction = copy_checkpoint(tmp_path), 5, 1.25
    steps = collect(ros_node, StepInfo, '/zeus/step')
    procs = {'sim_node': start_node(spawn, 'sim_node', {'family': FAMILY,
                                                        'command_timeout': 5.0})}
    for name, extra in (('context_node', {}), ('policy_node', {'context_timeout': 5.0})):
        procs[name] = start_node(spawn, name, {'weights': weights, 'backend': 'onnx', **extra})
    driver = LockstepDriver(ros_node)
    driver.wait_ready()
    rewards = episode_rewards(ros_node, driver, steps, seed, friction)

    onnx_model = OnnxInferenceModel.load(weights)
    for name in ('context_node', 'policy_node'):
        assert f'onnx, graphs from {onnx_model.export_dir}' in procs[name].output()
    assert not (weights / 'onnx').exists()   # the checkpoint is left as it was
    # The nodes ran the same graphs as this process: the same episode, bit for bit.
    expected = run_episode(onnx_model, FAMILY, friction, seed)
    assert_same_rewards(rewards, expected.rewards)
    # Not torch's: actions 1e-6 apart send the walker elsewhere, to a return
    # close to torch's (measured: 926 against 903).
    torch_run = run_episode(InferenceModel.load(weights), FAMILY, friction, seed)
    assert not np.array_equal(expected.rewards, torch_run.rewards)
    assert abs(expected.episode_return - torch_run.episode_return) \
        <= 0.1 * abs(torch_run.episode_return)


@pytest.mark.ros   # starts processes (the trainer, the export or bench command): not a unit test
def test_the_inference_bench_times_both_backends_on_the_same_steps(tmp_path):
    """A pass of research/benchmarks/bench_inference.py small enough to be no measurement."""
    out = tmp_path / 'figures.json'
    bench = REPO / 'research' / 'benchmarks' / 'bench_inference.py'
    done = subprocess.run([sys.executable, str(bench),
                           '--weights', str(WALKER_WEIGHTS), '--steps', '3', '--rounds', '1',
                           '--json', str(out)], cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    [figures] = json.loads(out.read_text())
    assert figures['steps'] == 3 and figures['largest_difference'] <= TOLERANCE
    for backend in ('torch', 'onnx'):
        for part in ('context_node', 'policy_node'):
            assert figures[f'{backend}_{part}_wall_us'] > 0
    assert 'onnx/torch' in done.stdout
