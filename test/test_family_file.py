"""Family files (#48): the schema, the edit kinds on a real MuJoCo model, every bad input."""

from pathlib import Path
import shutil

from conftest import REPO
import mujoco
import numpy as np
import pytest
import yaml

from sim_node.env import make_env
from sim_node.families import get_sim_family, SimFamily
from sim_node.family_edits import family_model, load_family_file
from sim_node.family_env import FamilyEnv
from sim_node.family_file import FamilyFileError, read_family_file

HOPPER = REPO / 'examples' / 'hopper' / 'hopper.yaml'
BODY, SITE, GEOM = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_SITE, mujoco.mjtObj.mjOBJ_GEOM


def hopper_doc() -> dict:
    return yaml.safe_load(HOPPER.read_text())


def written(tmp_path: Path, doc: dict | str, name: str = 'robot.yaml') -> Path:
    """Write a family file beside a copy of the Hopper's MJCF; return its path."""
    shutil.copy(HOPPER.parent / 'hopper.xml', tmp_path / 'hopper.xml')
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc))
    return path


def refusal(path: Path) -> str:
    with pytest.raises(FamilyFileError) as caught:
        load_family_file(path)
    error, message = caught.value, str(caught.value)
    assert '\n' not in message and message.startswith(f'{path}: '), message
    assert (error.origin, message) == (str(path), f'{path}: {error.field}: {error.reason}')
    return message


# -- the worked example ---------------------------------------------------------------
def test_the_hopper_file_is_a_family_every_tool_takes_by_name():
    spec = load_family_file(HOPPER)
    assert isinstance(spec, SimFamily) and get_sim_family(spec.name) is spec
    assert spec.param_names == ('floor_friction', 'leg_length')
    # log-uniform quantiles of [0.5, 2] at 1/4 and 3/4, times the listed lengths
    assert [round(f, 6) for f, _ in spec.train] == [0.707107, 0.707107, 1.414214, 1.414214]
    assert {length for _, length in spec.train} == {0.42, 0.54}
    assert (1.0, 0.34) in spec.extrapolation and (0.2, 0.5) in spec.extrapolation
    env = make_env(spec.name, (1.0, 0.5), seed=0)
    assert isinstance(env, FamilyEnv)
    assert env.layout.joint_names[0] == 'rootx' and env.layout.position_encoding[0] == 'drop'
    assert env.obs_dim == 12 and env.action_dim == 3 and env.control_timestep == 0.008


def test_loading_the_same_file_twice_is_harmless_and_a_builtin_name_is_refused(tmp_path):
    assert load_family_file(HOPPER) is not None
    assert load_family_file(HOPPER).name == 'hopper-friction-leg'
    doc = hopper_doc()
    doc['name'] = 'walker-walk-v0'
    assert 'is a built-in family' in refusal(written(tmp_path, doc))
    doc['name'] = 'hopper-friction-leg'
    doc['description'] = 'another robot of the same name'
    assert 'a different family file named' in refusal(written(tmp_path, doc))


# -- the edit kinds ------------------------------------------------------------------
def test_a_friction_swap_is_a_direct_write_that_changes_only_friction():
    env = make_env(load_family_file(HOPPER).name, (1.0, 0.5), seed=0)
    env.reset(seed=3)
    for _ in range(20):
        env.step(np.full(3, 0.3))
    before = {name: getattr(env.model, name).copy() for name in
              ('geom_friction', 'geom_size', 'body_pos', 'body_mass', 'geom_pos')}
    qpos = env.data.qpos.copy()
    prepared = env.prepare_values((0.3, 0.5))
    assert prepared.model is None          # no compile: MuJoCo allows this field live
    env.apply_prepared(prepared)
    assert np.all(env.model.geom_friction[:, 0] == 0.3)
    assert np.array_equal(env.model.geom_friction[:, 1:], before['geom_friction'][:, 1:])
    for name in ('geom_size', 'body_pos', 'body_mass', 'geom_pos'):
        assert np.array_equal(getattr(env.model, name), before[name]), name
    assert np.array_equal(env.data.qpos, qpos) and env.param_values == (0.3, 0.5)


def end_of_leg(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """World position of the leg capsule's lower end-cap centre."""
    g = mujoco.mj_name2id(model, GEOM, 'leg_geom')
    return data.geom_xpos[g] - model.geom_size[g, 1] * data.geom_xmat[g].reshape(3, 3)[:, 2]


def test_a_length_swap_moves_what_hangs_from_the_segments_end_and_keeps_the_state():
    env = make_env(load_family_file(HOPPER).name, (1.0, 0.5), seed=0)
    env.reset(seed=3)
    for _ in range(10):
        env.step(np.full(3, 0.2))
    model, data = env.model, env.data
    mujoco.mj_forward(model, data)   # mj_step leaves the kinematics one substep behind qpos
    foot = mujoco.mj_name2id(model, BODY, 'foot')
    knee = data.xanchor[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, 'leg_joint')].copy()
    ankle_from_end = data.xpos[foot] - end_of_leg(model, data)
    qpos, qvel, leg_mass = data.qpos.copy(), data.qvel.copy(), model.body_mass[3]
    prepared = env.prepare_values((1.0, 0.58))
    assert prepared.model is not None
    env.apply_prepared(prepared)
    # The segment is 0.58 m from the knee (which stays) to its end ...
    assert np.linalg.norm(end_of_leg(model, data) - knee) == pytest.approx(0.58, abs=1e-9)
    # ... and the foot hangs from that end as it did.
    assert np.allclose(data.xpos[foot] - end_of_leg(model, data), ankle_from_end, atol=1e-9)
    assert model.body_mass[3] > leg_mass           # keep_density: a longer leg is heavier
    assert np.array_equal(data.qpos, qpos) and np.array_equal(data.qvel, qvel)


def test_keep_mass_keeps_the_segments_body_mass(tmp_path):
    doc = hopper_doc()
    doc['name'] = 'hopper-keep-mass'
    doc['parameters'][1]['edit']['mass_rule'] = 'keep_mass'
    spec = load_family_file(written(tmp_path, doc))
    short, long = (family_model(spec).compile((1.0, v)) for v in (0.3, 0.6))
    assert short.body_mass[3] == pytest.approx(long.body_mass[3], rel=1e-12)
    assert not np.allclose(short.body_inertia[3], long.body_inertia[3])


def test_a_length_that_would_invert_the_segment_is_refused():
    spec = load_family_file(HOPPER)
    with pytest.raises(ValueError, match='would invert the segment'):
        family_model(spec).compile((1.0, -0.1))
    with pytest.raises(ValueError, match='outside the allowed range'):
        make_env(spec.name, (1.0, 0.5)).prepare_values((1.0, 0.0))


@pytest.mark.parametrize('edit, field, value', [
    ({'kind': 'damping', 'joints': ['leg_joint']}, 'dof_damping', 2.5),
    ({'kind': 'gear', 'actuators': ['leg_motor']}, 'actuator_gear', 150.0),
    ({'kind': 'mass', 'body': 'foot'}, 'body_mass', 7.0),
])
def test_the_other_edit_kinds_set_their_field(tmp_path, edit, field, value):
    doc = hopper_doc()
    doc['name'] = f'hopper-{edit["kind"]}'
    doc['parameters'][1] = {'name': 'p', 'edit': edit, 'default': value,
                            'live_range': [0.5, 300.0], 'train': [value]}
    xml = (HOPPER.parent / 'hopper.xml').read_text().replace(
        'gear="200.0" joint="leg_joint"', 'gear="200.0" joint="leg_joint" name="leg_motor"')
    path = written(tmp_path, doc)
    (tmp_path / 'hopper.xml').write_text(xml)
    model = family_model(load_family_file(path)).compile((1.0, value))
    index = {'dof_damping': (4,), 'actuator_gear': (1, 0), 'body_mass': (4,)}[field]
    assert getattr(model, field)[index] == pytest.approx(value)


# -- bad input: one line naming the file and the field -----------------------------------
def test_malformed_yaml_names_the_line(tmp_path):
    message = refusal(written(tmp_path, 'name: x\nmodel: [unclosed\n'))
    assert 'malformed YAML' in message and 'line' in message


@pytest.mark.parametrize('where, path', [
    (lambda d: d, 'colour'),
    (lambda d: d['task'], 'task.colour'),
    (lambda d: d['task']['reward'][0], 'task.reward[0].colour'),
    (lambda d: d['parameters'][1]['edit'], 'parameters[1].edit.colour'),
    (lambda d: d['task']['healthy'], 'task.healthy.colour'),
])
def test_an_unknown_field_is_named_at_any_level(tmp_path, where, path):
    doc = hopper_doc()
    where(doc)['colour'] = 'red'
    assert refusal(written(tmp_path, doc)).endswith(f': {path}: unknown field')


@pytest.mark.parametrize('change, path, reason', [
    (lambda d: d['parameters'][1]['edit'].update(geom='shin'), 'parameters[1].edit.geom',
     "no geom named 'shin'"),
    (lambda d: d['parameters'][0]['edit'].update(all_geoms=False, geoms=['ground']),
     'parameters[0].edit.geoms', "no geom named 'ground'"),
    (lambda d: d['task']['healthy'].update(angle_joint='hip'), 'task.healthy.angle_joint',
     "no joint named 'hip'"),
    (lambda d: d['task']['reward'][0].update(body='pelvis'), 'task.reward[0].body',
     "no body named 'pelvis'"),
    (lambda d: d['observation'].update(joints=['rootz', 'knee']), 'observation.joints[1]',
     "no joint named 'knee'"),
    (lambda d: d['parameters'][1].update(train=[0.42, 0.9]), 'parameters[1].train',
     '0.9 is outside live_range [0.25, 0.6]'),
    (lambda d: d['parameters'][0]['train'].update(range=[0.01, 2.0]),
     'parameters[0].train.range', 'inside live_range'),
    (lambda d: d['parameters'][1].update(extrapolation=[0.34, 0.54]),
     'parameters[1].extrapolation', '0.54 is a train value'),
    (lambda d: d['parameters'][1].update(live_range=[-0.1, 0.6]), 'parameters[1].live_range',
     'inverted'),
    (lambda d: d['parameters'][1]['edit'].update(geom='floor'), 'parameters[1].edit.geom',
     'not a capsule or cylinder'),
    (lambda d: d['control'].update(period=0.005), 'control.period', 'multiple of'),
    (lambda d: d['parameters'][1].update(train={'range': [0.3, 0.6], 'count': 40}),
     'parameters', '80 train tasks'),
    (lambda d: d['parameters'][1].update(name='seed'), 'parameters[1].name',
     'a parameter of the sim node itself'),
    (lambda d: d['parameters'][1].update(name='floor_friction'), 'parameters[1].name',
     'declared twice'),
    (lambda d: d['parameters'][1].update(name='leg-length'), 'parameters[1].name',
     'should match pattern'),
    (lambda d: d['parameters'][1]['edit'].update(mass_rule='keep_volume'),
     'parameters[1].edit.mass_rule', "'keep_density' or 'keep_mass'"),
])
def test_each_bad_value_is_one_line_naming_the_field(tmp_path, change, path, reason):
    doc = hopper_doc()
    change(doc)
    message = refusal(written(tmp_path, doc))
    assert f': {path}: ' in message and reason in message, message


def test_a_model_mujoco_cannot_compile_is_quoted(tmp_path):
    path = written(tmp_path, hopper_doc())
    xml = (tmp_path / 'hopper.xml').read_text()
    (tmp_path / 'hopper.xml').write_text(xml.replace('joint="foot_joint"', 'joint="ankle"'))
    message = refusal(path)
    assert ': model.mjcf: MuJoCo cannot compile the model: ' in message
    assert 'ankle' in message       # MuJoCo's own words, on the same line


def test_a_missing_model_file_is_named(tmp_path):
    doc = hopper_doc()
    doc['model']['mjcf'] = 'nowhere.xml'
    message = refusal(written(tmp_path, doc))
    assert ': model.mjcf: ' in message and 'nowhere.xml' in message


def test_reading_alone_needs_no_model_checks():
    """The MuJoCo-free half (what a checkpoint's metadata uses) reads the same file."""
    spec = read_family_file(HOPPER)
    assert spec.param_names == ('floor_friction', 'leg_length') and len(spec.sha256) == 64


# -- a dm_control suite domain and task by name ----------------------------------------
SLIPPERY_CHEETAH = """
name: cheetah-file-slippery
model: {suite: cheetah}
task: {suite_task: run}
control: {period: 0.01, horizon: 1000}
parameters:
  - name: friction
    edit: {kind: friction, all_geoms: true}
    default: 0.15
    live_range: [0.01, 3.0]
    train: [0.05, 0.06, 0.07, 0.08, 0.25, 0.3, 0.35, 0.4]
    interpolation: [0.12, 0.15, 0.18, 0.2]
    extrapolation: [0.02, 0.03, 0.035, 0.04, 0.5, 0.6, 0.8, 1.0]
"""


def model_differences(a: mujoco.MjModel, b: mujoco.MjModel) -> list[str]:
    return [name for name in dir(a) if not name.startswith(('_', 'tex_'))
            and isinstance(getattr(a, name), np.ndarray)
            and not np.array_equal(getattr(a, name), getattr(b, name))]


def test_a_suite_task_by_name_runs_as_the_builtin_family_does(tmp_path):
    """cheetah-run-slippery written as a file: the same model and, over a swap, the same steps."""
    from sim_node.env import build_model
    from sim_node.families import FAMILIES
    path = tmp_path / 'cheetah.yaml'
    path.write_text(SLIPPERY_CHEETAH)
    spec = load_family_file(path)
    builtin = FAMILIES['cheetah-run-slippery']
    assert spec.train == tuple((v,) for v in builtin.train)
    for value in (0.05, 0.6):
        mine, theirs = family_model(spec).compile((value,), low_res=True), \
            build_model(builtin, value)
        # The built-in also gives the ground the cheetah class's torsional and rolling
        # friction (0.1, 0.1 against MuJoCo's 0.005, 0.0001); at condim 3 they act on nothing.
        assert model_differences(mine, theirs) == ['geom_friction']
        assert np.array_equal(mine.geom_friction[:, 0], theirs.geom_friction[:, 0])
        assert np.array_equal(mine.geom_friction[1:], theirs.geom_friction[1:])
        assert mine.geom_condim[0] == 3
    ours, builtins = make_env(spec.name, (0.3,), seed=4), make_env(builtin.name, (0.3,), seed=4)
    assert np.array_equal(ours.reset(seed=7), builtins.reset(seed=7))
    actions = np.random.default_rng(0).uniform(-1, 1, (200, 6))
    for i, action in enumerate(actions):
        if i == 100:
            for env in (ours, builtins):
                env.apply_prepared(env.prepare_values((0.05,)))
        a, b = ours.step(action), builtins.step(action)
        assert np.array_equal(a.observation, b.observation) and a.reward == b.reward, i


CARTPOLE_LENGTH = """
name: cartpole-file-length
model: {suite: cartpole}
task: {suite_task: swingup}
control: {period: 0.01, horizon: 1000}
parameters:
  - name: pole_length
    unit: m
    edit: {kind: length, geom: pole_1, mass_rule: keep_mass}
    default: 1.0
    live_range: [0.2, 2.0]
    train: [0.8, 0.85, 0.9, 0.95, 1.05, 1.1, 1.15, 1.2]
    interpolation: [0.875, 0.975, 1.0, 1.125]
    extrapolation: [0.3, 0.33, 0.36, 0.4, 1.6, 1.63, 1.66, 1.7]
"""


def test_cartpole_swingup_length_as_a_file_is_the_builtin_family_exactly(tmp_path):
    """A built-in written as a file: for every split value its compiled model, field for field."""
    from sim_node.env import build_model
    from sim_node.families import FAMILIES
    path = tmp_path / 'cartpole.yaml'
    path.write_text(CARTPOLE_LENGTH)
    spec = load_family_file(path)
    builtin = FAMILIES['cartpole-swingup-length']
    for split in ('train', 'interpolation', 'extrapolation'):
        assert spec.split(split) == tuple((v,) for v in builtin.split(split))
        for (value,) in spec.split(split):
            assert model_differences(family_model(spec).compile((value,), low_res=True),
                                     build_model(builtin, value)) == [], value
    ours, builtins = make_env(spec.name, (1.0,), seed=2), make_env(builtin.name, (1.0,), seed=2)
    assert np.array_equal(ours.reset(seed=5), builtins.reset(seed=5))
    for i, action in enumerate(np.random.default_rng(1).uniform(-1, 1, (150, 1))):
        if i == 50:
            for env in (ours, builtins):
                env.apply_prepared(env.prepare_values((1.66,)))
        a, b = ours.step(action), builtins.step(action)
        assert np.array_equal(a.observation, b.observation) and a.reward == b.reward, i


def test_keep_density_on_a_geom_of_explicit_mass_is_refused(tmp_path):
    path = tmp_path / 'cartpole.yaml'
    path.write_text(CARTPOLE_LENGTH.replace('keep_mass', 'keep_density'))
    message = refusal(path)
    assert ": parameters[0].edit.mass_rule: geom 'pole_1' has an explicit mass (0.1 kg)" \
        in message and 'write keep_mass' in message


@pytest.mark.parametrize('change, path, reason', [
    ('model: {suite: cheetah}', 'model.suite', "no domain 'cheeta'"),
    ('task: {suite_task: run}', 'task.suite_task', "no task 'sprint'"),
])
def test_an_unknown_suite_domain_or_task_is_named(tmp_path, change, path, reason):
    text = SLIPPERY_CHEETAH.replace(change, change.replace('cheetah', 'cheeta')
                                    .replace('run', 'sprint'))
    (tmp_path / 'bad.yaml').write_text(text)
    message = refusal(tmp_path / 'bad.yaml')
    assert f': {path}: ' in message and reason in message, message


def test_a_model_needs_one_source_and_a_task_one_kind(tmp_path):
    both = SLIPPERY_CHEETAH.replace('model: {suite: cheetah}',
                                    'model: {suite: cheetah, mjcf: hopper.xml}')
    (tmp_path / 'both.yaml').write_text(both)
    assert ': model: needs exactly one of mjcf' in refusal(tmp_path / 'both.yaml')
    doc = hopper_doc()
    doc['task']['suite_task'] = 'hop'
    assert ': task: needs exactly one of suite_task and reward' in refusal(written(tmp_path, doc))


# -- a length given by fromto, with sites and geoms at both ends -----------------------
ARM = """<mujoco>
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 0 1"/>
      <geom name="upper" type="capsule" fromto="0 0 0 0.3 0 0" size="0.02"/>
      <site name="elbow_marker" pos="0.3 0 0.02"/>
      <site name="shoulder_marker" pos="0.02 0 0"/>
      <geom name="shoulder_cap" type="sphere" pos="0 0 0" size="0.03"/>
      <geom name="elbow_cap" type="sphere" pos="0.3 0 0" size="0.025"/>
      <geom name="elbow_guard" type="capsule" fromto="0.26 0 0 0.3 0 0" size="0.03"/>
      <body name="lower" pos="0.3 0 0">
        <joint name="elbow" type="hinge" axis="0 0 1"/>
        <geom name="lower" type="capsule" fromto="0 0 0 0.2 0 0" size="0.02"/>
        <site name="tip" pos="0.2 0 0"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="shoulder"/><motor joint="elbow"/></actuator>
</mujoco>"""

ARM_FAMILY = """name: arm-upper-length
model: {mjcf: arm.xml}
task: {reward: [{term: control_cost, weight: 1.0}]}
control: {period: 0.01, horizon: 100}
parameters:
  - name: upper_length
    unit: m
    edit: {kind: length, geom: upper, mass_rule: keep_mass}
    default: 0.3
    live_range: [0.05, 0.6]
    train: [0.2, 0.4]
"""


def test_a_fromto_segment_moves_sites_geoms_and_bodies_at_its_free_end_only(tmp_path):
    (tmp_path / 'arm.xml').write_text(ARM)
    (tmp_path / 'arm.yaml').write_text(ARM_FAMILY)
    family = family_model(load_family_file(tmp_path / 'arm.yaml'))
    model = family.compile((0.45,))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)

    def where(kind, name):
        i = mujoco.mj_name2id(model, kind, name)
        return {SITE: data.site_xpos, GEOM: data.geom_xpos, BODY: data.xpos}[kind][i]
    assert np.allclose(where(BODY, 'lower'), [0.45, 0, 0])
    assert np.allclose(where(SITE, 'tip'), [0.65, 0, 0])
    assert np.allclose(where(SITE, 'elbow_marker'), [0.45, 0, 0.02])
    assert np.allclose(where(GEOM, 'elbow_cap'), [0.45, 0, 0])
    assert np.allclose(where(GEOM, 'elbow_guard'), [0.43, 0, 0])    # given by fromto
    assert np.allclose(where(SITE, 'shoulder_marker'), [0.02, 0, 0])   # the fixed end's
    assert np.allclose(where(GEOM, 'shoulder_cap'), [0, 0, 0])
    upper = mujoco.mj_name2id(model, GEOM, 'upper')
    assert model.geom_size[upper, 1] == pytest.approx(0.225)          # half of 0.45
    assert model.body_mass[1] == pytest.approx(family.base.body_mass[1])   # keep_mass
    with pytest.raises(ValueError, match='would invert the segment'):
        family.compile((-0.2,))


def test_the_resampling_rate_is_the_trainers_swap_probability_unless_overridden(tmp_path):
    from zeus_ros.learning_tools.train import family_config
    doc = hopper_doc()
    doc['name'] = 'hopper-resampled'
    doc['training']['resample_rate'] = 0.02
    spec = load_family_file(written(tmp_path, doc))
    assert family_config(spec.name).train_swap_prob == 0.02
    assert family_config(spec.name, train_swap_prob=0.5).train_swap_prob == 0.5
    assert family_config(spec.name).episode_steps == 1000
    assert family_config(load_family_file(HOPPER).name).train_swap_prob == 0.0


def test_a_site_distance_reward_reads_the_sites_where_the_length_puts_them(tmp_path):
    (tmp_path / 'arm.xml').write_text(ARM.replace(
        '<worldbody>', '<worldbody>\n    <site name="target" pos="0.5 0 0"/>'))
    (tmp_path / 'arm.yaml').write_text(ARM_FAMILY.replace(
        'name: arm-upper-length', 'name: arm-reach').replace(
        '{reward: [{term: control_cost, weight: 1.0}]}',
        '{reward: [{term: site_distance, site: tip, target_site: target, weight: 2.0}]}'))
    env = make_env(load_family_file(tmp_path / 'arm.yaml').name, (0.3,), seed=0)
    env.reset(seed=0)
    assert env.step(np.zeros(2)).reward == pytest.approx(0.0, abs=1e-9)   # tip on target
    env.set_values((0.45,))
    assert env.step(np.zeros(2)).reward == pytest.approx(-2.0 * 0.15, abs=1e-9)
    doc = yaml.safe_load((tmp_path / 'arm.yaml').read_text())
    doc['task']['reward'][0]['target_site'] = 'goal'
    (tmp_path / 'arm.yaml').write_text(yaml.safe_dump(doc))
    assert ": task.reward[0].target_site: the model has no site named 'goal'" in \
        refusal(tmp_path / 'arm.yaml')


def test_friction_by_class_sets_the_geoms_of_that_class_and_an_unknown_class_is_named(tmp_path):
    xml = (HOPPER.parent / 'hopper.xml').read_text().replace(
        '<motor ctrllimited="true" ctrlrange="-.4 .4"/>',
        '<motor ctrllimited="true" ctrlrange="-.4 .4"/>\n    <default class="sole">'
        '<geom friction="2.0"/></default>').replace(
        'friction="2.0" pos="-0.065 0 0.1"', 'class="sole" pos="-0.065 0 0.1"')
    doc = hopper_doc()
    doc['name'] = 'hopper-sole'
    doc['parameters'][0]['edit'] = {'kind': 'friction', 'geom_class': 'sole'}
    path = written(tmp_path, doc)
    (tmp_path / 'hopper.xml').write_text(xml)
    model = family_model(load_family_file(path)).compile((0.3, 0.5))
    foot = mujoco.mj_name2id(model, GEOM, 'foot_geom')
    assert model.geom_friction[foot, 0] == 0.3
    assert [f for i, f in enumerate(model.geom_friction[:, 0]) if i != foot] == \
        [1.0, 0.9, 0.9, 0.9]        # the floor's and the other links' own
    doc['parameters'][0]['edit']['geom_class'] = 'heel'
    assert ": parameters[0].edit.geom_class: the model has no default class 'heel'" in \
        refusal(written(tmp_path, doc, 'heel.yaml'))


def test_a_free_joint_cannot_be_observed_and_the_file_says_so(tmp_path):
    (tmp_path / 'arm.xml').write_text(ARM.replace(
        '</worldbody>', '<body name="ball" pos="1 0 0"><freejoint/>'
                        '<geom type="sphere" size=".05"/></body>\n  </worldbody>'))
    (tmp_path / 'arm.yaml').write_text(ARM_FAMILY.replace('arm-upper-length', 'arm-ball'))
    assert refusal(tmp_path / 'arm.yaml').endswith(
        ": observation.joints: joint '#2 (unnamed)' is not a hinge or slide joint")
    doc = yaml.safe_load(ARM_FAMILY.replace('arm-upper-length', 'arm-ball'))
    doc['observation'] = {'joints': ['shoulder', 'elbow']}    # the arm's alone: fine
    (tmp_path / 'arm.yaml').write_text(yaml.safe_dump(doc))
    env = make_env(load_family_file(tmp_path / 'arm.yaml').name, (0.3,))
    assert env.joint_names == ('shoulder', 'elbow') and env.obs_dim == 6
