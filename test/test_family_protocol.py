"""Every family answers one typed interface: its spec `SimFamily`, its env `FamilyEnv`."""

import inspect
import math
from types import SimpleNamespace

from conftest import REPO
import pytest
from sim_node.env import make_env
from sim_node.family_edits import load_family_file
from sim_node.family_file import FileFamilySpec
from sim_node.families import (EPISODE_STEPS, FAMILIES, FamilySpec, GOAL_FAMILIES,
                               GoalFamilySpec, SIM_FAMILIES, SimFamily, values_with)
from sim_node.family_env import EnvPhysics, FamilyEnv, PreparedValues

# One family of each env class: ParamEnv (dm_control), SawyerPegEnv and FileEnv (a family
# file's: the Hopper example, registered by the fixture).
HOPPER_FILE = REPO / 'examples' / 'hopper' / 'hopper.yaml'
ENV_FAMILIES = ('walker-walk-v0', 'sawyer-peg-v0', HOPPER_FILE)


def protocol_members(protocol) -> set[str]:
    """Return the names a Protocol declares (its own, not object's or Protocol's machinery)."""
    return {name for name in vars(protocol) if not name.startswith('_')}


@pytest.mark.parametrize('family', list(SIM_FAMILIES))
def test_every_family_spec_is_a_sim_family_with_a_horizon(family):
    spec = SIM_FAMILIES[family]
    assert isinstance(spec, SimFamily)
    for name in protocol_members(SimFamily):
        assert hasattr(spec, name), name
    assert isinstance(spec.episode_steps, int) and spec.episode_steps > 0
    assert len(spec.param_names) == len(spec.live_params) >= 1


def test_the_horizons_are_the_tasks_own():
    assert {spec.episode_steps for spec in FAMILIES.values()} == {EPISODE_STEPS} == {1000}
    assert {spec.episode_steps for spec in GOAL_FAMILIES.values()} == {40}   # Table 9


@pytest.mark.parametrize('spec_class', [FamilySpec, GoalFamilySpec, FileFamilySpec])
def test_the_spec_methods_take_what_the_protocol_says(spec_class):
    for name in ('split', 'check_param'):
        wanted = list(inspect.signature(getattr(SimFamily, name)).parameters)
        assert list(inspect.signature(getattr(spec_class, name)).parameters) == wanted, name


def test_something_that_is_not_a_family_is_no_sim_family():
    class HalfSpec:   # a spec without a horizon or splits
        name, domain, param_names = 'x', 'y', ('z',)
    assert not isinstance(HalfSpec(), SimFamily)


def test_values_with_makes_a_value_tuple_from_names_and_refuses_what_a_set_would():
    spec = SIM_FAMILIES['sawyer-peg-v0']
    assert values_with(spec, (0.5, 0.0), {'goal_y': 0.07}) == (0.5, 0.07)
    assert values_with(spec, (0.5, 0.0), {'goal_y': 0.07, 'goal_x': 0.6}) == (0.6, 0.07)
    assert values_with(spec, (0.5, 0.0), {}) == (0.5, 0.0)
    for changes in ({'goal_z': 0.1}, {'goal_x': 0.9}, {'goal_x': math.nan}, {'goal_y': 'far'}):
        with pytest.raises(ValueError):
            values_with(spec, (0.5, 0.0), changes)
    walker = SIM_FAMILIES['walker-walk-v0']
    assert values_with(walker, (0.7,), {'friction': 2}) == (2.0,)
    with pytest.raises(ValueError, match='unknown parameter'):
        values_with(walker, (0.7,), {'foot_length': 0.1})


@pytest.fixture(scope='module', params=ENV_FAMILIES, ids=str)
def env(request):
    family = request.param
    if family == HOPPER_FILE:
        family = load_family_file(HOPPER_FILE).name
    return make_env(family)


def test_every_env_class_is_a_family_env(env):
    assert isinstance(env, FamilyEnv)
    assert isinstance(env.spec, SimFamily) and env.spec.name == env.family
    assert isinstance(env.physics, EnvPhysics)
    assert env.episode_steps == env.spec.episode_steps        # the family's horizon
    assert env.param_names == env.spec.param_names
    assert isinstance(env.param_values, tuple) and len(env.param_values) == len(env.param_names)


def test_the_env_methods_take_what_the_protocol_says(env):
    """Each method the protocol lists, with its parameters by name (arity and keywords)."""
    for name in protocol_members(FamilyEnv):
        declared = inspect.getattr_static(FamilyEnv, name)
        if isinstance(declared, property):
            assert hasattr(env, name), name
            continue
        wanted = list(inspect.signature(declared).parameters)
        assert list(inspect.signature(getattr(type(env), name)).parameters) == wanted, name


def test_a_swap_goes_through_prepared_values(env):
    values = env.param_values
    prepared = env.prepare_values(values)
    assert isinstance(prepared, PreparedValues) and prepared.values == values
    env.apply_prepared(prepared)
    env.set_values(values)
    assert env.param_values == values


def test_no_env_keeps_a_scalar_or_by_name_twin(env):
    for twin in ('param_value', 'set_param', 'prepare_param', 'set_goal'):
        assert not hasattr(env, twin), twin


def test_an_env_without_one_member_is_no_family_env(env):
    """The isinstance check above can fail: drop any one member and it does."""
    members = {name: getattr(env, name) for name in protocol_members(FamilyEnv)}
    assert isinstance(SimpleNamespace(**members), FamilyEnv)
    for missing in ('set_values', 'episode_steps', 'copy_state_from', 'spec'):
        assert not isinstance(SimpleNamespace(**{n: v for n, v in members.items()
                                                 if n != missing}), FamilyEnv), missing
