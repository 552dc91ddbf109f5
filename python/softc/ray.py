"""Batches of softc runs as Ray tasks, on one machine or a cluster.

    import ray, softc.ray
    ray.init()                                   # or ray.init(address="auto") on a cluster
    results = softc.ray.map("examples/pressure_optimization.soft",
                            [{"p_max": p} for p in (5e3, 10e3, 15e3)])
    [r["loss"] for r in results]

Each task compiles the scene once per worker process and keeps it for the worker's later
tasks. Results come back in the order of ``param_dicts`` and are identical to evaluating the
param sets one by one with :meth:`softc.Scene.run` (or :meth:`~softc.Scene.loss_and_grad` with
``grad=True``): softc's runs are deterministic whatever the machine's thread count. On a
cluster the script and its mesh must be readable at the same path on every node.
"""

from __future__ import annotations

import os
from typing import Any, Dict, List, Mapping, Optional, Sequence

__all__ = ["map"]

_COMPILE_KEYS = ("backend", "precision", "threads", "adapter", "linear_solver")
_RUN_KEYS = ("steps", "dt", "inputs")
_GRAD_KEYS = ("checkpoint", "memory_budget")

# Scenes compiled in this worker process, by script and compile options.
_CACHE: Dict[Any, Any] = {}


def _scene(path: str, compile_options: Mapping[str, Any]):
    import softc

    key = (path, tuple(sorted(compile_options.items())))
    scene = _CACHE.get(key)
    if scene is None:
        scene = softc.compile(path, **compile_options)
        _CACHE[key] = scene
    return scene


def evaluate(path: str, params: Mapping[str, Any], compile_options: Mapping[str, Any],
             run_options: Mapping[str, Any], grad: bool):
    """One param set: what a task runs (also usable serially)."""
    scene = _scene(path, compile_options)
    if grad:
        return scene.loss_and_grad(params, **run_options)
    return scene.run(params, **run_options)


def _task_options(compile_options: Mapping[str, Any], cpus: float) -> Dict[str, Any]:
    """A task's compile options: it runs on the CPUs Ray reserved for it (with one task per
    core, softc's default of a thread per core would put every core's threads on each core)."""
    return {"threads": max(1, int(cpus)), **compile_options}


def map(  # noqa: A001 - the name the API promises
    path,
    param_dicts: Sequence[Mapping[str, Any]],
    *,
    grad: bool = False,
    num_cpus: Optional[float] = None,
    **options,
) -> List[Any]:
    """Evaluate every param set of ``param_dicts`` as a Ray task; results in order.

    Each result is :meth:`softc.Scene.run`'s dict, or with ``grad=True`` the ``(loss, grads)``
    pair of :meth:`softc.Scene.loss_and_grad`. ``options``: the compile options of
    :func:`softc.compile` (``backend``, ``precision``, ``threads``, ``adapter``,
    ``linear_solver``) and the run options (``steps``, ``dt``, ``inputs``; with ``grad``,
    ``checkpoint`` and ``memory_budget``). ``num_cpus``: CPUs Ray reserves per task (default
    1, or ``threads`` when given); a task runs on that many threads unless ``threads`` says
    otherwise. Ray is started locally if it is not running; call
    ``ray.init(address=...)`` first to use a cluster. A failed run raises its
    :class:`softc.SimulationError` here (a compile error, :class:`softc.CompileError`).
    """
    import ray

    known = set(_COMPILE_KEYS) | set(_RUN_KEYS) | (set(_GRAD_KEYS) if grad else set())
    unknown = set(options) - known
    if unknown:
        raise TypeError(f"softc.ray.map: unknown options {sorted(unknown)}; known: {sorted(known)}")
    path = os.path.abspath(os.fspath(path))
    if not os.path.exists(path):
        raise FileNotFoundError(f"no script at `{path}`")
    compile_options = {k: options[k] for k in _COMPILE_KEYS if k in options}
    run_options = {k: options[k] for k in (*_RUN_KEYS, *_GRAD_KEYS) if k in options}
    # Compile here first: a script with errors fails once, with its diagnostics, not per task.
    _scene(path, compile_options)
    if not ray.is_initialized():
        ray.init(ignore_reinit_error=True, log_to_driver=False)
    cpus = num_cpus if num_cpus is not None else float(compile_options.get("threads") or 1)
    task_options = _task_options(compile_options, cpus)
    task = ray.remote(num_cpus=cpus, max_retries=0)(evaluate)
    refs = [task.remote(path, dict(p), task_options, run_options, grad) for p in param_dicts]
    try:
        return ray.get(refs)
    except ray.exceptions.RayTaskError as e:
        cause = e.as_instanceof_cause()
        # The original softc exception (SimulationError, CompileError, ValueError) when Ray
        # kept it.
        if isinstance(cause, Exception) and hasattr(e, "cause") and e.cause is not None:
            raise e.cause from None
        raise cause from None
