"""A softc scene as a differentiable loss inside a PyTorch model.

    import softc, softc.torch, torch
    scene = softc.compile("examples/pressure_optimization.soft")
    loss_fn = softc.torch.SceneLoss(scene)
    p = torch.tensor(12e3, dtype=torch.float64, requires_grad=True)
    loss = loss_fn(p_max=p)          # 0-d tensor: softc's forward run
    loss.backward()                  # p.grad: softc's adjoint, d loss / d p_max

The gradient is softc's own (reverse-mode kernels, or the implicit function theorem for static
solves), not a PyTorch re-implementation: it equals :meth:`softc.Scene.loss_and_grad`.

A batch: give the script's inputs as tensors with a leading batch dimension (``inputs=``), and
params either at their declared shape (shared by the batch) or with the same leading batch
dimension (one value per scene, e.g. the pressures a controller network outputs per target).
The result is then a tensor of the ``B`` per-scene losses.
"""

from __future__ import annotations

from typing import Any, Dict, Mapping, Optional

import numpy as np
import torch

from . import ParamError, Scene

__all__ = ["SceneLoss"]


def _as_numpy(value) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().to(torch.float64).numpy()
    return np.asarray(value, dtype=np.float64)


class _SceneFunction(torch.autograd.Function):
    """Forward: softc's run (with its adjoint when a param needs a gradient); backward: the
    stored gradients times the incoming one. The adjoint runs with the forward pass, as softc's
    backward pass replays the forward run it differentiates."""

    @staticmethod
    def forward(ctx, module: "SceneLoss", spec: Dict[str, Any], *tensors):
        names = spec["names"]
        batched = spec["batched"]
        batch = spec["batch"]
        inputs = spec["inputs"]
        need_grad = spec["need_grad"]
        values = [_as_numpy(t) for t in tensors]
        losses = []
        grads = []  # per scene: {name: array}
        for b in range(batch if batch is not None else 1):
            params = {
                n: (v[b] if batched[i] else v) for i, (n, v) in enumerate(zip(names, values))
            }
            scene_inputs = None
            if inputs is not None:
                scene_inputs = {n: a[b] for n, a in inputs.items()}
            if need_grad:
                loss, g = module.scene.loss_and_grad(
                    params, inputs=scene_inputs, **module.grad_options
                )
                grads.append(g)
            else:
                summary = module.scene.run(params, inputs=scene_inputs, **module.run_options)
                loss = summary["loss"]
            if loss is None:
                raise ValueError(f"{module.scene.path}: the script has no `loss` to return")
            losses.append(loss)
        ctx.spec = spec
        ctx.grads = grads
        ctx.dtypes = [(t.dtype, t.device, t.shape) for t in tensors]
        dtype = spec["dtype"]
        device = spec["device"]
        if batch is None:
            return torch.tensor(losses[0], dtype=dtype, device=device)
        return torch.tensor(losses, dtype=dtype, device=device)

    @staticmethod
    def backward(ctx, grad_output):
        spec = ctx.spec
        names = spec["names"]
        batched = spec["batched"]
        batch = spec["batch"]
        upstream = grad_output.detach().cpu().to(torch.float64).numpy()
        out = []
        for i, name in enumerate(names):
            dtype, device, shape = ctx.dtypes[i]
            if not ctx.needs_input_grad[2 + i]:
                out.append(None)
                continue
            if batch is None:
                g = float(upstream) * np.asarray(ctx.grads[0][name], dtype=np.float64)
            elif batched[i]:
                g = np.stack(
                    [upstream[b] * np.asarray(ctx.grads[b][name]) for b in range(batch)]
                )
            else:
                g = sum(upstream[b] * np.asarray(ctx.grads[b][name]) for b in range(batch))
            out.append(torch.as_tensor(np.asarray(g), dtype=dtype, device=device).reshape(shape))
        return (None, None, *out)


class SceneLoss(torch.nn.Module):
    """A scene's loss as a ``torch.nn.Module``.

    ``forward(inputs=None, **params)`` takes tensors (or numbers, arrays) for any subset of the
    script's params, SI units; the others stay at the script's values. It returns the loss as a
    0-d tensor, or with a batch (see the module's doc) a tensor of per-scene losses; ``backward``
    fills the param tensors' ``.grad`` from softc's adjoint. float64 and float32 tensors work
    (softc computes in the scene's precision and converts). ``run_options``: ``steps``, ``dt``,
    ``checkpoint``, ``memory_budget`` as for :meth:`softc.Scene.loss_and_grad`.
    """

    def __init__(self, scene: Scene, **run_options):
        super().__init__()
        if not scene.has_loss:
            raise ValueError(f"{scene.path}: the script has no `loss`; SceneLoss needs one")
        known = {"steps", "dt", "checkpoint", "memory_budget"}
        unknown = set(run_options) - known
        if unknown:
            raise TypeError(
                f"SceneLoss: unknown run options {sorted(unknown)}; known: {sorted(known)}"
            )
        self.scene = scene
        self.grad_options = dict(run_options)
        self.run_options = {k: v for k, v in run_options.items() if k in ("steps", "dt")}

    def forward(self, inputs: Optional[Mapping[str, Any]] = None, **params):
        names = list(params)
        tensors = []
        for n in names:
            if n not in self.scene.params:
                hint = " (it is an input: pass it in inputs=)" if n in self.scene.inputs else ""
                raise ParamError(
                    f"the script has no param `{n}`{hint}; its params: {list(self.scene.params)}"
                )
            v = params[n]
            if not isinstance(v, torch.Tensor):
                v = torch.as_tensor(np.asarray(v, dtype=np.float64))
            tensors.append(v)
        batch = None
        batch_inputs = None
        if inputs is not None:
            batch_inputs = {}
            for n, a in inputs.items():
                if n not in self.scene.inputs:
                    raise ParamError(
                        f"the script has no input `{n}`; its inputs: {list(self.scene.inputs)}"
                    )
                arr = _as_numpy(a)
                shape = self.scene.inputs[n].shape
                if arr.shape[1:] != shape:
                    raise ParamError(
                        f"input `{n}`: expected a batch of shape (B, {', '.join(map(str, shape))})"
                        f", got {tuple(arr.shape)}"
                    )
                if batch is not None and arr.shape[0] != batch:
                    raise ValueError("the inputs' batch dimensions differ")
                batch = arr.shape[0]
                batch_inputs[n] = arr
        batched = []
        for n, t in zip(names, tensors):
            shape = self.scene.params[n].shape
            if tuple(t.shape) == shape:
                batched.append(False)
            elif t.dim() == len(shape) + 1 and tuple(t.shape[1:]) == shape:
                if batch is not None and t.shape[0] != batch:
                    raise ValueError(
                        f"param `{n}` has a batch of {t.shape[0]}, the batch is {batch}"
                    )
                batch = t.shape[0]
                batched.append(True)
            else:
                raise ParamError(
                    f"param `{n}` has shape {shape}; got a tensor of shape {tuple(t.shape)} "
                    f"(give shape {shape}, or (B, *{shape}) for one value per scene of a batch)"
                )
        floats = [t for t in tensors if t.is_floating_point()]
        dtype = floats[0].dtype if floats else torch.float64
        device = floats[0].device if floats else torch.device("cpu")
        spec = {
            "names": names,
            "batched": batched,
            "batch": batch,
            "inputs": batch_inputs,
            "need_grad": torch.is_grad_enabled() and any(t.requires_grad for t in tensors),
            "dtype": dtype,
            "device": device,
        }
        return _SceneFunction.apply(self, spec, *tensors)
