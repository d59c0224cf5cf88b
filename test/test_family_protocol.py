"""Every family answers one typed interface: its spec `SimFamily`, its env `FamilyEnv`."""

import inspect

import pytest
from sim_node.families import (EPISODE_STEPS, FAMILIES, FamilySpec, GOAL_FAMILIES,
                               GoalFamilySpec, SIM_FAMILIES, SimFamily)


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
