"""Every family answers one typed interface: its spec `SimFamily`, its env `FamilyEnv`."""

import inspect
import math

import pytest
from sim_node.families import (EPISODE_STEPS, FAMILIES, FamilySpec, GOAL_FAMILIES,
                               GoalFamilySpec, SIM_FAMILIES, SimFamily, values_with)


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


@pytest.mark.parametrize('spec_class', [FamilySpec, GoalFamilySpec])
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
