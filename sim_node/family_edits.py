"""The edit kinds of a family file, applied to its MJCF through `mujoco.MjSpec`.

Why MjSpec and not the XML edits of the built-in families: a family file names
a geom, a class or a joint and MjSpec finds it the way MuJoCo does (defaults
already applied, whatever the MJCF's orientation or `fromto` spelling), and
each build starts from a fresh parse of the file, so the model of a value
tuple is a pure function of it (the trainer and the sim node compile the same
model). A live swap does not call `spec.recompile(model, data)` on the
control loop: that would compile there. It compiles the new model on the
swap worker and copies it into the live model in place (`model_copy`), which
keeps MjData, the state, untouched, as recompile does. Friction needs no
compile at all: it is a real-valued field MuJoCo allows to be written live
(`FileEnv` writes `geom_friction` directly).

`FamilyModel` checks a family against its model (every name it uses exists,
the MJCF compiles, each length segment is one) and builds models for value
tuples; every refusal is a `FamilyFileError` naming the file and the field.
"""

from __future__ import annotations

from dataclasses import dataclass
import functools
import importlib
from pathlib import Path
import xml.etree.ElementTree as ElementTree

import mujoco
import numpy as np

from sim_node.families import register_family
from sim_node.family_file import (DampingEdit, FamilyFileError, FileFamilySpec, FrictionEdit,
                                  GearEdit, LengthEdit, MassEdit, Parameter, read_family_file)
from sim_node.layout import DROPPED_JOINTS, ObservationLayout
from sim_node.structures import DOMAIN_STRUCTURES, DomainStructure

_OBJ = mujoco.mjtObj


def model_source(family: FileFamilySpec) -> tuple[str, dict, float | None]:
    """Return the family's MJCF, the files it includes, and a total mass to scale to (or None).

    A suite domain's MJCF is dm_control's. Its compiler's `settotalmass` is
    deprecated in MuJoCo 3.x: it is taken out and done on the compiled model,
    as the built-in families do (`sim_node.env`), so both compile the same model.
    """
    domain = family.document.model.suite
    if domain is None:
        return family.model_xml, {}, None
    from dm_control import suite   # only a suite family needs dm_control
    domains = sorted({d for d, _ in suite.ALL_TASKS})
    if domain not in domains:
        raise FamilyFileError(family.origin, 'model.suite',
                              f'dm_control has no domain {domain!r}; one of '
                              f'{", ".join(domains)}')
    xml, assets = importlib.import_module(f'dm_control.suite.{domain}').get_model_and_assets()
    root = ElementTree.fromstring(xml)
    compiler = root.find('compiler')
    total = compiler.attrib.pop('settotalmass', None) if compiler is not None else None
    return (ElementTree.tostring(root, encoding='unicode'), assets,
            None if total is None else float(total))


def new_spec(model_xml: str, assets: dict, origin: str, low_res: bool = False) -> mujoco.MjSpec:
    """Parse the family's MJCF; `low_res`: builtin textures at 2x2 (a swap keeps the live ones)."""
    try:
        spec = mujoco.MjSpec.from_string(model_xml, include=assets or None)
    except ValueError as error:
        raise FamilyFileError(origin, 'model.mjcf', 'MuJoCo cannot read it: '
                              f'{_one_line(error)}') from None
    if low_res:
        for texture in spec.textures:
            if texture.builtin != mujoco.mjtBuiltin.mjBUILTIN_NONE:
                texture.width = texture.height = 2
    return spec


def _one_line(error: Exception) -> str:
    return ' '.join(str(error).split())


@dataclass(frozen=True)
class Segment:
    """A link segment in its body's frame: the end fixed at the joint, the axis, the length."""

    geom: str
    body: str
    fixed: np.ndarray
    axis: np.ndarray     # unit vector from the fixed end towards the free end
    length: float


def _segment(model: mujoco.MjModel, geom_name: str, fromto: np.ndarray) -> Segment | str:
    """Read a capsule/cylinder geom's segment, or say why it is none.

    `fromto` is the spec's: where the MJCF gives the ends, they are taken as
    written (the compiled pos and quat hold them only to rounding); otherwise
    they come from the compiled centre, orientation and half-length.
    """
    g = mujoco.mj_name2id(model, _OBJ.mjOBJ_GEOM, geom_name)
    if int(model.geom_type[g]) not in (int(mujoco.mjtGeom.mjGEOM_CAPSULE),
                                       int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
        return f'geom {geom_name!r} is not a capsule or cylinder: it has no length to set'
    b = int(model.geom_bodyid[g])
    if not np.isnan(fromto[0]):
        ends = (np.array(fromto[:3]), np.array(fromto[3:]))
    else:
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, model.geom_quat[g])
        half = float(model.geom_size[g, 1])
        ends = (model.geom_pos[g] - half * mat.reshape(3, 3)[:, 2],
                model.geom_pos[g] + half * mat.reshape(3, 3)[:, 2])
    # The fixed end is the one at the body's joint (the body's origin if it has none):
    # what hangs from the other end moves with the length.
    anchor = model.jnt_pos[model.body_jntadr[b]] if model.body_jntnum[b] else np.zeros(3)
    near = int(np.linalg.norm(ends[1] - anchor) < np.linalg.norm(ends[0] - anchor))
    fixed, free = ends[near], ends[1 - near]
    length = float(np.linalg.norm(free - fixed))
    return Segment(geom_name, mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, b), fixed.copy(),
                   (free - fixed) / length, length)


def set_length(spec: mujoco.MjSpec, segment: Segment, length: float) -> None:
    """Make the segment `length` long: its geom, and what hangs from its free end, moved.

    "Hangs from its free end": the body's child bodies (their subtrees move with
    them), sites and other geoms that lie past the segment's middle along its
    axis. Their offsets from the end are kept.
    """
    if not length > 0:
        raise ValueError(f'length {length:g} of geom {segment.geom!r} would invert the '
                         f'segment (it must stay above 0)')
    shift = (length - segment.length) * segment.axis
    body = spec.body(segment.body)
    middle = segment.length / 2

    def past_middle(pos: np.ndarray) -> bool:
        return float(np.dot(np.asarray(pos) - segment.fixed, segment.axis)) > middle

    for child in body.bodies:
        if past_middle(child.pos):
            child.pos = np.asarray(child.pos) + shift
    for site in body.sites:
        if past_middle(site.pos):
            site.pos = np.asarray(site.pos) + shift
    for geom in body.geoms:
        if geom.name == segment.geom:
            continue
        ends = np.asarray(geom.fromto)
        if np.isnan(ends[0]):
            if past_middle(geom.pos):
                geom.pos = np.asarray(geom.pos) + shift
        elif past_middle((ends[:3] + ends[3:]) / 2):   # a geom given by its ends
            geom.fromto = ends + np.concatenate([shift, shift])
    geom = spec.geom(segment.geom)
    geom.fromto = np.concatenate([segment.fixed, segment.fixed + length * segment.axis])


class FamilyModel:
    """A family file's model, checked; compiles the model of any value tuple.

    Construction checks everything that needs the model and raises
    `FamilyFileError` naming the first problem. `compile(values)` is safe on any
    thread (each call parses its own spec).
    """

    def __init__(self, family: FileFamilySpec):
        self.family = family
        self.origin = family.origin
        self.xml, self.assets, self.total_mass = model_source(family)
        self._model_field = 'model.mjcf' if family.document.model.mjcf else 'model.suite'
        self.base = self._compile(self._new_spec(), self._model_field)
        self._check_geom_order()
        self._check_suite_task()
        self._check_names()
        self.segments = {p.name: self._checked_segment(i, p)
                         for i, p in enumerate(family.document.parameters)
                         if isinstance(p.edit, LengthEdit)}
        self.friction_geoms = {p.name: self._friction_ids(p)
                               for p in family.document.parameters
                               if isinstance(p.edit, FrictionEdit)}
        self._check_period()

    # -- checks ---------------------------------------------------------------
    def _new_spec(self, low_res: bool = False) -> mujoco.MjSpec:
        return new_spec(self.xml, self.assets, self.origin, low_res)

    def _check_geom_order(self) -> None:
        # Friction edits address geoms by index, in the spec (a build) and in the model
        # (a live write): the compiler keeps the spec's order, and this says so if not.
        spec = self._new_spec()   # held: its elements are views into it
        names = [g.name for g in spec.geoms]
        compiled = [mujoco.mj_id2name(self.base, _OBJ.mjOBJ_GEOM, i) or ''
                    for i in range(self.base.ngeom)]
        if names != compiled:
            raise self._refuse(self._model_field, 'its geoms compile in another order than '
                                                  'they are declared: friction edits would miss')

    def _check_suite_task(self) -> None:
        task, domain = self.family.document.task.suite_task, self.family.document.model.suite
        if task is None:
            return
        from dm_control import suite
        tasks = sorted(t for d, t in suite.ALL_TASKS if d == domain)
        if task not in tasks:
            raise self._refuse('task.suite_task', f"dm_control's {domain} has no task {task!r}; "
                                                  f'one of {", ".join(tasks)}')

    def _refuse(self, path: str, reason: str) -> FamilyFileError:
        return FamilyFileError(self.origin, path, reason)

    def _compile(self, spec: mujoco.MjSpec, path: str) -> mujoco.MjModel:
        try:
            model = spec.compile()
        except ValueError as error:
            raise self._refuse(path, f'MuJoCo cannot compile the model: {_one_line(error)}') \
                from None
        self._scale_total_mass(model)
        return model

    def _scale_total_mass(self, model: mujoco.MjModel) -> None:
        if self.total_mass is not None:
            mujoco.mj_setTotalmass(model, self.total_mass)
            mujoco.mj_setConst(model, mujoco.MjData(model))

    def _has(self, kind: mujoco.mjtObj, name: str) -> bool:
        return mujoco.mj_name2id(self.base, kind, name) >= 0

    def _names_used(self):
        """(field path, object kind, name) of every name the file uses."""
        doc = self.family.document
        for i, p in enumerate(doc.parameters):
            yield from ((f'parameters[{i}].edit.{field}', kind, name)
                        for field, kind, name in _edit_names(p))
        for i, term in enumerate(doc.task.reward):
            if getattr(term, 'body', None) is not None:
                yield f'task.reward[{i}].body', _OBJ.mjOBJ_BODY, term.body
            for field in ('site', 'target_site'):
                if getattr(term, field, None) is not None:
                    yield f'task.reward[{i}].{field}', _OBJ.mjOBJ_SITE, getattr(term, field)
        healthy = doc.task.healthy
        if healthy is not None:
            yield 'task.healthy.body', _OBJ.mjOBJ_BODY, healthy.body
            if healthy.angle_joint is not None:
                yield 'task.healthy.angle_joint', _OBJ.mjOBJ_JOINT, healthy.angle_joint
        if doc.observation.joints != 'all':
            for i, name in enumerate(doc.observation.joints):
                yield f'observation.joints[{i}]', _OBJ.mjOBJ_JOINT, name

    def _check_names(self) -> None:
        for path, kind, name in self._names_used():
            if kind == 'class':
                if not self._spec_default(name):
                    raise self._refuse(path, f'the model has no default class {name!r}')
            elif not self._has(kind, name):
                what = kind.name.removeprefix('mjOBJ_').lower()
                raise self._refuse(path, f'the model has no {what} named {name!r}')

    def _spec_default(self, name: str) -> bool:
        spec = self._new_spec()
        return spec.find_default(name) is not None

    def _checked_segment(self, index: int, param: Parameter) -> Segment:
        spec = self._new_spec()   # held while its geom is read (a view into it)
        geom = spec.geom(param.edit.geom)
        found = _segment(self.base, param.edit.geom, np.asarray(geom.fromto))
        if isinstance(found, str):
            raise self._refuse(f'parameters[{index}].edit.geom', found)
        if param.edit.mass_rule == 'keep_density' and not np.isnan(geom.mass):
            # An explicit mass wins over the density: the mass would stay, not the density.
            raise self._refuse(f'parameters[{index}].edit.mass_rule',
                               f'geom {param.edit.geom!r} has an explicit mass '
                               f'({geom.mass:g} kg), which a length does not change: '
                               f'write keep_mass')
        return found

    def _friction_ids(self, param: Parameter) -> np.ndarray:
        edit: FrictionEdit = param.edit
        if edit.all_geoms:
            return np.arange(self.base.ngeom)
        if edit.geoms:
            return np.array([mujoco.mj_name2id(self.base, _OBJ.mjOBJ_GEOM, n)
                             for n in edit.geoms])
        spec = self._new_spec()   # held: its geoms are views into it
        ids = [i for i, g in enumerate(spec.geoms) if g.classname.name == edit.geom_class]
        return np.array(ids, dtype=int)

    def _check_period(self) -> None:
        period, step = self.family.document.control.period, self.base.opt.timestep
        substeps = round(period / step)
        if substeps < 1 or not np.isclose(substeps * step, period, rtol=1e-6):
            raise self._refuse('control.period', f"must be a multiple of the model's timestep "
                                                 f'{step:g} s, got {period:g}')

    # -- building ---------------------------------------------------------------
    def edited_spec(self, values: tuple[float, ...], low_res: bool = False) -> mujoco.MjSpec:
        """Return a fresh spec with every parameter's edit made (ValueError: why not)."""
        spec = self._new_spec(low_res)
        for param, value in zip(self.family.document.parameters, values, strict=True):
            self._edit(spec, param, float(value))
        return spec

    def _edit(self, spec: mujoco.MjSpec, param: Parameter, value: float) -> None:
        edit = param.edit
        if isinstance(edit, FrictionEdit):
            for g in self.friction_geoms[param.name]:
                spec.geoms[g].friction[0] = value
        elif isinstance(edit, LengthEdit):
            set_length(spec, self.segments[param.name], value)
        elif isinstance(edit, DampingEdit):
            for name in edit.joints:
                spec.joint(name).damping[0] = value
        elif isinstance(edit, GearEdit):
            for name in edit.actuators:
                spec.actuator(name).gear[0] = value
        # MassEdit acts on the compiled model (`_set_masses`): with inertia from the
        # geoms, a body's own mass attribute is not what the compiler uses.

    def compile(self, values: tuple[float, ...], low_res: bool = False) -> mujoco.MjModel:
        """Compile the model of `values` (in `param_names` order), masses as the mass rules say."""
        model = self.edited_spec(values, low_res).compile()
        self._scale_total_mass(model)
        self._set_masses(model, values)
        return model

    def _set_masses(self, model: mujoco.MjModel, values: tuple[float, ...]) -> None:
        targets = {}
        for param, value in zip(self.family.document.parameters, values, strict=True):
            if isinstance(param.edit, MassEdit):
                targets[param.edit.body] = float(value)
            elif isinstance(param.edit, LengthEdit) and param.edit.mass_rule == 'keep_mass':
                body = self.segments[param.name].body
                targets.setdefault(body, float(self.base.body_mass[self._body_id(body)]))
        for body, mass in targets.items():
            b = self._body_id(body)
            ratio = mass / model.body_mass[b]
            # A uniform change of density: mass and inertia scale together.
            model.body_mass[b] *= ratio
            model.body_inertia[b] *= ratio
        if targets:
            mujoco.mj_setConst(model, mujoco.MjData(model))

    def _body_id(self, name: str) -> int:
        return mujoco.mj_name2id(self.base, _OBJ.mjOBJ_BODY, name)

    # -- what a controller sees ------------------------------------------------
    def layout(self) -> ObservationLayout:
        """Return the observation: the declared joints, encoded as `layout_from_model` does."""
        model, joints = self.base, self.family.document.observation.joints
        ids = range(model.njnt) if joints == 'all' else \
            [mujoco.mj_name2id(model, _OBJ.mjOBJ_JOINT, n) for n in joints]
        names, encodings = [], []
        for j in ids:
            name = mujoco.mj_id2name(model, _OBJ.mjOBJ_JOINT, j) or f'#{j} (unnamed)'
            kind = int(model.jnt_type[j])
            if kind not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
                raise self._refuse('observation.joints', f'joint {name!r} is not a hinge or '
                                                         f'slide joint')
            names.append(name)
            free_hinge = kind == mujoco.mjtJoint.mjJNT_HINGE and not model.jnt_limited[j]
            encodings.append('drop' if name in DROPPED_JOINTS else
                             'angle' if free_hinge else 'raw')
        return ObservationLayout(tuple(names), tuple(encodings))

    def structure(self) -> DomainStructure:
        """Return the robot as the controllers check it (`sim_node.structures`)."""
        layout = self.layout()
        actuators = tuple(mujoco.mj_id2name(self.base, _OBJ.mjOBJ_ACTUATOR, i) or f'actuator{i}'
                          for i in range(self.base.nu))
        return DomainStructure(layout.joint_names, layout.position_encoding, None, actuators,
                               self.family.document.control.period)


def _edit_names(param: Parameter):
    edit = param.edit
    if isinstance(edit, FrictionEdit):
        yield from (('geoms', _OBJ.mjOBJ_GEOM, n) for n in edit.geoms)
        if edit.geom_class is not None:
            yield 'geom_class', 'class', edit.geom_class
    elif isinstance(edit, LengthEdit):
        yield 'geom', _OBJ.mjOBJ_GEOM, edit.geom
    elif isinstance(edit, MassEdit):
        yield 'body', _OBJ.mjOBJ_BODY, edit.body
    elif isinstance(edit, DampingEdit):
        yield from (('joints', _OBJ.mjOBJ_JOINT, n) for n in edit.joints)
    elif isinstance(edit, GearEdit):
        yield from (('actuators', _OBJ.mjOBJ_ACTUATOR, n) for n in edit.actuators)


@functools.lru_cache(maxsize=16)
def family_model(family: FileFamilySpec) -> FamilyModel:
    """Return the checked model of a family (one per family in a process)."""
    return FamilyModel(family)


def register_checked(family: FileFamilySpec) -> FileFamilySpec:
    """Check a family against its model, then make it known by name in this process."""
    checked = family_model(family)
    DOMAIN_STRUCTURES[family.domain] = checked.structure()
    try:
        register_family(family, family.sha256)
    except ValueError as error:
        raise FamilyFileError(family.origin, 'name', str(error)) from None
    return family


def load_family_file(path: str | Path) -> FileFamilySpec:
    """Read, check (schema, values, model) and register a family file; FamilyFileError: why not.

    Afterwards its name works wherever a built-in family's does (`make_env`,
    `get_sim_family`, the checkpoint metadata's checks).
    """
    return register_checked(read_family_file(path))
