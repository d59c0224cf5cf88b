"""Export a checkpoint's deployed networks as ONNX, with a JSON that says how to call them.

    export_onnx(checkpoint, out_dir)      # -> out_dir/onnx.json + one .onnx per graph

The graphs are what `InferenceModel` runs at deployment, for every method:

* ``context.onnx``: the method's `deployed_context`: (rows [B, k, row_dim]
  float32, mask [B, k] bool) -> latent [B, context_dim]; a privileged method
  (oracle) reads true_param [B, P] instead. Absent when the latent is empty
  (context_dim 0, `sac`): the latent is then a [B, 0] array.
* ``phi.onnx``: obs [B, obs_dim] -> features [B, feature_dim].
* ``actor.onnx``: (features, latent) -> action [B, action_dim], tanh of the mean.
* ``decoder.onnx``: latent -> normalised parameter estimates [B, P]; absent
  when the method has no read-out. Physical value = normalised * scale + offset
  (``estimate`` in the JSON).

The batch axis B is dynamic; the nodes run B = 1. ``onnx.json`` names each
graph's inputs and outputs with dtype and shape, the SHA-256 and size of
each file, the opset and exporter, the SHA-256 of the checkpoint's
model.safetensors the graphs came from (``source.model_sha256``: a loader
compares it to see that an export is stale) and the checkpoint's whole
metadata.json (``metadata``), so an export directory is deployable alone.

The exporter is torch's TorchScript-based one (``dynamo=False``): it needs
nothing beyond torch and the pinned onnx, where the torch.export-based
default also needs onnxscript.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import shutil
from typing import TYPE_CHECKING
import warnings

import onnx
import torch
from torch import nn

from zeus_ros.deploy.checkpoint import (CheckpointError, load_model, MODEL_FILE, resolve_dir,
                                        sha256_file, write_metadata)
from zeus_ros.deploy.metadata import CheckpointMetadata

if TYPE_CHECKING:
    from zeus_ros.core.methods import ContextMethod
    from zeus_ros.core.networks import Actor

MANIFEST = 'onnx.json'
MANIFEST_FORMAT = 1
OPSET = 17          # LayerNormalization (phi's) is an ONNX op from opset 17
DEFAULT_SUBDIR = 'onnx'
_DTYPES = {onnx.TensorProto.FLOAT: 'float32', onnx.TensorProto.BOOL: 'bool'}


class _Context(nn.Module):
    """The method's deployed context over (rows, mask[, true_param])."""

    def __init__(self, method: ContextMethod):
        super().__init__()
        self.method = method
        # Registered so that the modules' weights are part of this graph.
        self.nets = nn.ModuleDict(method.inference_modules())

    def forward(self, rows: torch.Tensor, mask: torch.Tensor,
                true_param: torch.Tensor | None = None) -> torch.Tensor:
        return self.method.deployed_context(rows, mask, true_param)


class _Actor(nn.Module):
    def __init__(self, actor: Actor):
        super().__init__()
        self.actor = actor

    def forward(self, features: torch.Tensor, latent: torch.Tensor) -> torch.Tensor:
        return self.actor.mean_action(torch.cat([features, latent], dim=-1))


class _Decoder(nn.Module):
    def __init__(self, method: ContextMethod):
        super().__init__()
        self.method = method
        self.nets = nn.ModuleDict(method.inference_modules())

    def forward(self, latent: torch.Tensor) -> torch.Tensor | None:
        return self.method.decode(latent)


@torch.no_grad()
def _graphs(meta: CheckpointMetadata, method: ContextMethod,
            modules: dict[str, nn.Module]) -> dict:
    """Graph name -> (module, example inputs, input names, output name)."""
    k, row_dim, obs_dim = meta.context.k, meta.context.row_dim, meta.obs_layout.obs_dim
    dim = method.context_dim
    rows, mask = torch.zeros(1, k, row_dim), torch.ones(1, k, dtype=torch.bool)
    latent = torch.zeros(1, dim)
    features = modules['phi'](torch.zeros(1, obs_dim))
    graphs = {'phi': (modules['phi'], (torch.zeros(1, obs_dim),), ['obs'], 'features'),
              'actor': (_Actor(modules['actor']), (features, latent), ['features', 'latent'],
                        'action')}
    if dim > 0:
        args, names = ((rows, mask), ['rows', 'mask'])
        if method.needs_true_param:
            param = torch.zeros(1, method.param.param_dim)
            args, names = (rows, mask, param), ['rows', 'mask', 'true_param']
        graphs['context'] = (_Context(method), args, names, 'latent')
        if method.decode(latent) is not None:
            graphs['decoder'] = (_Decoder(method), (latent,), ['latent'], 'estimate')
    return graphs


def _export_graph(module: nn.Module, args: tuple, inputs: list, output: str,
                  path: Path) -> dict:
    """Write one graph; return its entry of the manifest, read back from the file."""
    dynamic = {name: {0: 'batch'} for name in [*inputs, output]}
    with warnings.catch_warnings():
        # The TorchScript exporter is chosen on purpose (see the module docstring);
        # its deprecation notices, its own and those of helpers it calls, say nothing new.
        warnings.simplefilter('ignore', DeprecationWarning)
        # The oracle's ParamScale.as_rows calls torch.as_tensor on the input tensor
        # itself (no copy, no constant): test_every_method_and_encoder_exports[oracle].
        warnings.filterwarnings('ignore', message='torch.as_tensor results are registered',
                                category=torch.jit.TracerWarning)
        torch.onnx.export(module.eval(), args, str(path), dynamo=False, input_names=inputs,
                          output_names=[output], opset_version=OPSET, dynamic_axes=dynamic)
    graph = onnx.load(str(path))
    with torch.no_grad():
        _name_output_sizes(graph, tuple(module(*args).shape))
    onnx.checker.check_model(graph, full_check=True)
    onnx.save(graph, str(path))
    return {'file': path.name, 'sha256': sha256_file(path), 'bytes': path.stat().st_size,
            # An input the graph does not read (the oracle's window) is not in it.
            'inputs': [_describe(v) for v in graph.graph.input],
            'outputs': [_describe(v) for v in graph.graph.output]}


def _name_output_sizes(graph: onnx.ModelProto, shape: tuple) -> None:
    """Write the output's sizes after the batch axis as numbers.

    The exporter leaves some symbolic (the actor's action comes out of a split,
    'Tanhaction_dim_1'); a reader of the graph alone should see action_dim.
    """
    dims = graph.graph.output[0].type.tensor_type.shape.dim
    for dim, size in zip(list(dims)[1:], shape[1:], strict=True):
        dim.dim_value = int(size)


def _describe(value: onnx.ValueInfoProto) -> dict:
    shape = [d.dim_param or d.dim_value for d in value.type.tensor_type.shape.dim]
    elem = value.type.tensor_type.elem_type
    return {'name': value.name, 'dtype': _DTYPES.get(elem, onnx.TensorProto.DataType.Name(elem)),
            'shape': shape}


def manifest_for(meta: CheckpointMetadata, method: ContextMethod, modules: dict[str, nn.Module],
                 out_dir: Path, source: Path) -> dict:
    """Export every graph of a loaded checkpoint into `out_dir`; return the manifest."""
    graphs = {name: _export_graph(*spec, out_dir / f'{name}.onnx')
              for name, spec in _graphs(meta, method, modules).items()}
    norm = meta.param_normalisation
    return {
        'format': 'zeus_ros onnx export', 'format_version': MANIFEST_FORMAT,
        'opset': OPSET, 'exporter': f'torch.onnx (TorchScript, dynamo=False), torch '
                                    f'{torch.__version__}, onnx {onnx.__version__}',
        'source': {'checkpoint': str(source), 'model_sha256': meta.files[MODEL_FILE].sha256},
        'method': meta.context.method, 'context_dim': method.context_dim,
        'needs_true_param': method.needs_true_param,
        'graphs': graphs,
        'empty_latent': 'context_dim 0: no context graph; the actor reads a [B, 0] latent',
        'estimate': {'formula': 'exp(normalised * scale + offset)' if norm.log
                     else 'normalised * scale + offset', 'offset': list(norm.offsets),
                     'scale': list(norm.scales), 'names': list(meta.names)},
        'metadata': meta.to_dict(),
    }


def export_onnx(checkpoint: str | Path, out_dir: str | Path | None = None,
                replace: bool = True) -> Path:
    """Export a checkpoint's graphs into `out_dir` (default: <checkpoint>/onnx); return it.

    Written to a temporary directory and renamed into place, so a reader never
    sees half an export. An export already there is replaced, unless not
    `replace`: then a finished export there (another process's, of the same
    weights) is kept and this one dropped.
    """
    source = resolve_dir(checkpoint)
    out = Path(out_dir) if out_dir is not None else source / DEFAULT_SUBDIR
    torch.set_num_threads(1)
    meta, method, modules = load_model(source)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f'.{out.name}.tmp-{os.getpid()}'
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        manifest = manifest_for(meta, method, modules, tmp, source.resolve())
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True))
        # The checkpoint's metadata beside the graphs: the directory loads on its own.
        write_metadata(tmp, meta)
        _move_into_place(tmp, out, replace)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _move_into_place(tmp: Path, out: Path, replace: bool) -> None:
    """Rename a finished export to `out` (moving an older one away first if `replace`)."""
    old = out.parent / f'.{out.name}.old-{os.getpid()}'
    if replace and out.exists():
        out.rename(old)
    try:
        tmp.rename(out)
    except OSError as error:
        if not (out / MANIFEST).exists():   # not another process's finished export
            raise CheckpointError(f'cannot write the ONNX export to {out}: {error}') from None
    shutil.rmtree(old, ignore_errors=True)
