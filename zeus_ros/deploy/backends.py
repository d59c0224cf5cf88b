"""Load a deployed checkpoint for the runtime a controller asks for: torch or ONNX Runtime.

`load_deployed(path, backend)` returns the torch `InferenceModel` or the
ONNX Runtime `OnnxInferenceModel`, both `DeployedModel`s. Its own module so
that the two runtimes' modules never import each other: `onnx_model` builds
on `inference`'s `DeployedModel`, and this module picks between them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from zeus_ros.deploy.inference import DeployedModel, InferenceModel

if TYPE_CHECKING:
    from pathlib import Path

# The `backend` a controller node (or `load_deployed`) accepts.
BACKENDS = ('torch', 'onnx')


def load_deployed(path: str | Path, backend: str = 'torch', **checks) -> DeployedModel:
    """Load a checkpoint for `backend` ('torch' or 'onnx'); `checks` as InferenceModel.load."""
    if backend == 'torch':
        return InferenceModel.load(path, **checks)
    if backend == 'onnx':
        # Imported here: a torch deployment never loads ONNX Runtime.
        from zeus_ros.deploy.onnx_model import OnnxInferenceModel
        return OnnxInferenceModel.load(path, **checks)
    raise ValueError(f'backend must be one of {BACKENDS}, got {backend!r}')
