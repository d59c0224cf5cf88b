"""Writing a newly compiled model into a live one of the same structure, in place.

A live swap compiles the model of the new values off the control loop and
copies it into the model the simulation steps, keeping MjData (the state)
untouched: `sim_node.env.ParamEnv` and `sim_node.file_env.FileEnv` both do.
"""

from __future__ import annotations

import mujoco
import numpy as np


class ModelWriter:
    """Writes a newly compiled model into a live one of the same structure, in place.

    A swap could put a new Physics in force (what `ParamEnv.set_values` does),
    but constructing one costs milliseconds of Python (dm_control's named
    indexing) and leaves cyclic garbage behind. Every family's edit changes
    values only (friction, sizes, positions, masses and what the compiler
    derives from them), never the structure, so copying every array and the
    `opt` and `stat` fields makes the live model equal to the new one, field
    for field. The textures (`build_model` compiles them at 2x2) and `vis`
    (rendering only, never edited) stay the live model's.
    """

    def __init__(self, live: mujoco.MjModel):
        self.live = live
        self.arrays = [name for name in dir(live) if not name.startswith(('_', 'tex_'))
                       and isinstance(getattr(live, name), np.ndarray)]
        self._targets = [getattr(live, name) for name in self.arrays]  # views, bound once
        self.structs = {name: [field for field in dir(getattr(live, name))
                               if not field.startswith('_')
                               and not callable(getattr(getattr(live, name), field))]
                        for name in ('opt', 'stat')}

    def write(self, model: mujoco.MjModel) -> None:
        """Copy `model` (of the same structure: `structure_of` equal) into the live model."""
        for target, name in zip(self._targets, self.arrays, strict=True):
            target[...] = getattr(model, name)
        for struct, fields in self.structs.items():
            source, target = getattr(model, struct), getattr(self.live, struct)
            for field in fields:
                value = getattr(source, field)
                if isinstance(value, np.ndarray):
                    getattr(target, field)[...] = value
                else:
                    setattr(target, field, value)


def structure_of(model: mujoco.MjModel) -> dict:
    """Return the model's sizes (nq, nbody, ngeom...): the same for every value of a family.

    The two that count texture pixels and bytes in all (`build_model`'s
    textures are smaller) are not part of it.
    """
    return {name: getattr(model, name) for name in dir(model)
            if name.startswith('n') and name not in ('ntexdata', 'nbuffer')
            and isinstance(getattr(model, name), int)}
