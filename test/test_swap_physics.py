"""A swap in two halves (prepare off the loop, apply in place) is exactly the trainer's set_values.

families.py's XML edit stays the one definition of each parameter: the sim
node compiles the edited XML (`build_model`) and writes that model into the
live one. These tests hold it to `ParamEnv.set_values` (a new Physics from the
same XML): same model, field for field, and bit-identical trajectories.
"""

import threading

import numpy as np
import pytest
from sim_node.env import build_model, build_physics, ParamEnv
from sim_node.families import FAMILIES
from sim_node.swaps import SwapQueue


def model_arrays(model):
    """Every array of the model but the textures' (build_model compiles them at 2x2)."""
    return {name: getattr(model, name) for name in dir(model)
            if not name.startswith(('_', 'tex_'))
            and isinstance(getattr(model, name), np.ndarray)}


def assert_structs_equal(model, expected):
    for struct in ('opt', 'stat'):
        source, target = getattr(model, struct), getattr(expected, struct)
        for field in dir(source):
            if not field.startswith('_') and not callable(getattr(source, field)):
                np.testing.assert_array_equal(getattr(source, field), getattr(target, field),
                                              err_msg=f'{struct}.{field}')


def swap_values(spec):
    lo, hi = spec.live_range
    return [spec.train[0], hi, lo, spec.train[-1], spec.default]


@pytest.mark.parametrize('family', list(FAMILIES))
def test_build_model_is_the_model_build_physics_compiles_but_its_textures(family):
    spec = FAMILIES[family]
    for value in swap_values(spec):
        alone, in_physics = build_model(spec, value), build_physics(spec, value).model.ptr
        expected = model_arrays(in_physics)
        assert model_arrays(alone).keys() == expected.keys()
        for name, array in model_arrays(alone).items():
            np.testing.assert_array_equal(array, expected[name], err_msg=name)
        assert_structs_equal(alone, in_physics)
        assert alone.nbuffer < in_physics.nbuffer / 100   # 2x2 textures: kilobytes, not 12 MB


@pytest.mark.parametrize('family', list(FAMILIES))
def test_prepare_and_apply_give_set_values_trajectory_bit_for_bit(family):
    """Five swaps mid-episode and an episode start in between, two seeds, every family."""
    spec = FAMILIES[family]
    values = swap_values(spec)
    for seed in (0, 1):
        reference = ParamEnv(family, spec.default, seed=seed, episode_steps=150)
        swapped = ParamEnv(family, spec.default, seed=seed, episode_steps=150)
        reference.reset(seed=seed)
        swapped.reset(seed=seed)
        sequence = np.random.RandomState(seed).uniform(-1, 1, (260, reference.action_dim))
        for i, action in enumerate(sequence):
            if i % 50 == 20:
                value = values[i // 50]
                reference.set_values((value,))
                swapped.apply_prepared(swapped.prepare_values((value,)))
            expected, result = reference.step(action), swapped.step(action)
            assert result.reward == expected.reward, (family, seed, i)
            np.testing.assert_array_equal(swapped.joint_positions(),
                                          reference.joint_positions())
            np.testing.assert_array_equal(swapped.joint_velocities(),
                                          reference.joint_velocities())
            if expected.truncated:
                reference.reset()
                swapped.reset()
        # ...and the live model is now the fresh compile of the last value, field for field
        # (textures included: the live model keeps its own).
        live, expected_model = swapped.physics.model.ptr, reference.physics.model.ptr
        for name in dir(live):
            if isinstance(getattr(live, name), np.ndarray):
                np.testing.assert_array_equal(getattr(live, name),
                                              getattr(expected_model, name), err_msg=name)
        assert_structs_equal(live, expected_model)


def test_prepare_values_leaves_the_env_alone_and_runs_on_any_thread():
    env = ParamEnv('walker-walk-v0', 1.0, seed=0)
    env.reset(seed=0)
    before = env.joint_positions()
    prepared = []
    worker = threading.Thread(target=lambda: prepared.append(env.prepare_values((0.4,))))
    worker.start()
    worker.join()
    assert env.param_values == (1.0,) and prepared[0].values == (0.4,)
    np.testing.assert_array_equal(env.joint_positions(), before)
    env.apply_prepared(prepared[0])
    assert env.param_values == (0.4,)
    assert env.physics.model.geom_friction[0, 0] == 0.4
    np.testing.assert_array_equal(env.joint_positions(), before)   # the state carried over


def test_prepare_values_refuses_a_value_outside_the_live_range():
    env = ParamEnv('walker-walk-v0', 1.0, seed=0)
    with pytest.raises(ValueError, match='outside the allowed range'):
        env.prepare_values((10.0,))


def rss_mb() -> float:
    with open('/proc/self/status') as status:
        for line in status:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024
    raise RuntimeError('no VmRSS in /proc/self/status')


def test_memory_stays_flat_over_300_swaps():
    """Issue #17.9: the sim's RSS grew ~12 MB at a time around swaps, up to ~220 MB.

    Not a leak: every model was freed (malloc's bytes in use stayed at 42.5 MB),
    but each swap built a new Physics around a 12 MB model (the skybox), and
    glibc kept the freed ones in its heap (malloc_trim gave 74 MB back). A swap
    now compiles a 25 kB model and writes it into the live one; the Physics
    stays. From RSS after 50 warm-up swaps, the old swap peaked 13-38 MB higher
    over the next 300; this one 0.1-2 MB (the allocator's own noise).
    """
    env = ParamEnv('walker-walk-v0', 0.7, seed=0)
    env.reset(seed=0)
    physics = env.physics
    swaps = SwapQueue(env.prepare_values)
    values = [0.4, 1.2, 0.8, 1.7, 0.5, 2.0]

    def swap_through_the_worker(i):
        swaps.push((values[i % len(values)],))
        env.apply_prepared(swaps.take_waiting())
        env.step(np.zeros(env.action_dim))
    try:
        for i in range(50):   # the worker thread, its arena, the cached low-res assets
            swap_through_the_worker(i)
        before = peak = rss_mb()
        for i in range(300):
            swap_through_the_worker(i)
            peak = max(peak, rss_mb())
    finally:
        swaps.close()
    assert env.physics is physics
    assert peak - before < 8.0, f'RSS rose {peak - before:.1f} MB over 300 swaps'
