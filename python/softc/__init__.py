"""softc from Python: differentiable simulation and optimization of pressure-driven soft actuators.

A ``.soft`` script is compiled once by softc's compiler (the same driver as the ``softc``
command line) and then run with any values of its params and inputs; runs and gradients are
computed by softc's own kernels and adjoints, and their numbers are bit-identical to
``softc run --set ...`` (and ``--grad``) with the same settings.

    import softc
    scene = softc.compile("examples/pressure_optimization.soft")
    loss, grads = scene.loss_and_grad({"p_max": 12e3})   # SI units: Pa
    summary = scene.run({"p_max": 12e3}, return_state=True)
    summary["x"].shape                                     # (nodes, 3), metres

``softc.torch.SceneLoss`` makes a scene a differentiable loss inside a PyTorch model, and
``softc.ray.map`` evaluates many param sets as Ray tasks.
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

from . import _softc
from ._softc import CompileError, SimulationError

__version__ = _softc.__version__


class ParamError(SimulationError, ValueError):
    """Values a run cannot take: a name the script does not declare, a wrong shape, a value in
    the wrong unit. The run does not start; catch it as a :class:`SimulationError` or a
    ``ValueError``. (A value outside a param's bounds is a :class:`SimulationError` with the
    command line's message.)"""


class SoftcWarning(UserWarning):
    """A run that ended without error but whose answer is doubtful or rests on a convention
    (the summary's ``warnings``, which ``softc run`` prints): linear tetrahedra of a nearly
    incompressible material, a static body free to rotate, a state the precision does not
    resolve, a loss taken ``at end`` while the state still moves."""


__all__ = [
    "compile",
    "quantity",
    "Scene",
    "Slot",
    "Mesh",
    "CompileError",
    "SimulationError",
    "ParamError",
    "SoftcWarning",
    "__version__",
]


@dataclass(frozen=True)
class Slot:
    """A param or input of a script. Values are in SI units (``unit``), row-major ``shape``."""

    name: str
    #: ``"param"``, ``"field"`` (one entry per element of ``set``) or ``"input"``.
    kind: str
    shape: Tuple[int, ...]
    unit: str
    lower: Optional[float]
    upper: Optional[float]
    #: The script's value: a float for a scalar, else an array of ``shape``.
    initial: Any
    set: Optional[str] = None

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) if self.shape else 1


@dataclass(frozen=True)
class Mesh:
    """The scene's mesh: nodes in metres, tets in the kernels' order (grouped by material).
    ``order`` is 1 (4-node tets) or 2 (10-node tets: ``elements`` holds each tet's corners, then
    its mid-edge nodes in VTK order; ``tets`` the corners alone; ``nodes`` every node)."""

    nodes: np.ndarray  # (n_nodes, 3) float64
    tets: np.ndarray  # (n_tets, 4) uint32
    order: int
    elements: np.ndarray  # (n_tets, 4 or 10) uint32
    node_sets: Dict[str, np.ndarray]
    element_sets: Dict[str, np.ndarray]
    fixed_nodes: np.ndarray


def quantity(text: str, unit: Optional[str] = None, name: str = "value") -> float:
    """A value written with its unit, in SI: ``quantity("12 kPa") == 12000.0``. With ``unit``
    (an SI unit such as ``"Pa"``), the value must have that dimension."""
    try:
        value, si = _softc.quantity(text)
    except ValueError as e:
        raise ParamError(f"{name} = {text!r} is not a number with a unit: {e}") from None
    if unit is not None and si != unit:
        raise ParamError(
            f"{name} = {text!r} is in {si}, but `{name}` is in {unit}: give a value in a unit of "
            f"the same dimension (or a float in {unit})"
        )
    return value


def _number(name: str, value, unit: str) -> float:
    """One entry of a param or input: a number, or a string with its unit; anything else
    (``True``, ``None``, bytes, a list where a number goes) is a :class:`ParamError`."""
    if isinstance(value, (str, np.str_)):
        return quantity(str(value), unit, name)
    if value is None or isinstance(value, (bool, np.bool_)) or not isinstance(
        value, (int, float, np.integer, np.floating)
    ):
        raise ParamError(
            f"`{name}` = {value!r}: give a number (in {unit}) or a value with its unit such as "
            f"\"3 kPa\""
        )
    return float(value)


def _shaped(values, shape):
    if not shape:
        return float(values[0])
    return np.asarray(values, dtype=np.float64).reshape(shape)


def compile(
    path,
    *,
    backend: str = "cpu",
    precision: Optional[str] = None,
    threads: Optional[int] = None,
    adapter: Optional[str] = None,
    linear_solver: str = "auto",
    warm_start: bool = False,
) -> "Scene":
    """Compile a ``.soft`` script for a device.

    ``backend``: ``"cpu"`` (Cranelift, default), ``"gpu"`` (WGSL through wgpu) or ``"interp"``
    (the kernel-IR interpreter). ``precision``: ``"f32"`` or ``"f64"`` (default: the script's
    ``precision``, else f64 on the cpu and f32 on the gpu). ``threads``: worker threads of the
    cpu backend. ``adapter``: part of a GPU adapter's name. ``linear_solver``: ``"auto"``
    (default: ``"direct"`` up to 100,000 free dofs, ``"amg"`` beyond), ``"direct"``, ``"amg"``
    or ``"krylov"`` for static and implicit solves. ``warm_start``: each static solve starts
    from the previous run's equilibrium instead of from rest, as an optimization in ``softc
    run`` does: in an optimization loop a solve then costs a few Newton iterations instead of a
    load continuation, but a run's result depends on the run before it to the solver's
    tolerance (not bit for bit ``softc run``'s). Raises :class:`CompileError` with
    ``.diagnostics`` when the script has errors.
    """
    path = os.fspath(path)
    if backend not in ("cpu", "gpu", "interp"):
        raise ValueError(
            f'backend = {backend!r}: expected "cpu", "gpu" or "interp" (the reference oracle '
            "is a test oracle, run by `softc run --backend reference`)"
        )
    if not os.path.exists(path):
        raise FileNotFoundError(f"no script at `{path}`")
    native = _softc.compile(
        path,
        backend=backend,
        precision=precision,
        threads=threads,
        adapter=adapter,
        linear_solver=linear_solver,
        warm_start=warm_start,
    )
    return Scene(native, path)


class Scene:
    """A compiled script bound to its mesh and a device, ready to run with any param values.

    Use :func:`compile` to make one. A scene runs one simulation at a time (calls from several
    threads wait for each other); the GIL is released while it simulates.
    """

    def __init__(self, native, path: str):
        self._native = native
        self.path = path
        self._describe = native.describe()
        slots = [
            Slot(
                name=s["name"],
                kind=s["kind"],
                shape=tuple(s["shape"]),
                unit=s["unit"],
                lower=s["lower"],
                upper=s["upper"],
                initial=_shaped(s["initial"], s["shape"]),
                set=s["set"],
            )
            for s in native.slots()
        ]
        #: The params in source order, by name.
        self.params: Dict[str, Slot] = {s.name: s for s in slots if s.kind != "input"}
        #: The inputs, by name.
        self.inputs: Dict[str, Slot] = {s.name: s for s in slots if s.kind == "input"}
        self._mesh: Optional[Mesh] = None
        self._state: Optional[Tuple[np.ndarray, np.ndarray]] = None

    def __repr__(self) -> str:
        d = self._describe
        return (
            f"softc.Scene({d['path']!r}, backend={d['backend']!r}, "
            f"integrator={d['integrator']!r}, params={list(self.params)}, "
            f"inputs={list(self.inputs)})"
        )

    @property
    def backend(self) -> str:
        return self._describe["backend"]

    @property
    def integrator(self) -> str:
        """``"explicit"``, ``"quasi_static"`` or ``"implicit_euler"``."""
        return self._describe["integrator"]

    @property
    def has_loss(self) -> bool:
        return self._describe["has_loss"]

    @property
    def mesh(self) -> Mesh:
        if self._mesh is None:
            m = self._native.mesh()
            self._mesh = Mesh(
                nodes=np.asarray(m["nodes"], dtype=np.float64).reshape(-1, 3),
                tets=np.asarray(m["tets"], dtype=np.uint32).reshape(-1, 4),
                order=int(m["order"]),
                elements=np.asarray(m["elements"], dtype=np.uint32).reshape(
                    -1, 10 if m["order"] == 2 else 4
                ),
                node_sets={k: np.asarray(v, dtype=np.uint32) for k, v in m["node_sets"].items()},
                element_sets={
                    k: np.asarray(v, dtype=np.uint32) for k, v in m["element_sets"].items()
                },
                fixed_nodes=np.asarray(m["fixed_nodes"], dtype=np.uint32),
            )
        return self._mesh

    def _values(self, params: Optional[Mapping], inputs: Optional[Mapping]):
        out = []
        for group, given, what in ((self.params, params, "param"), (self.inputs, inputs, "input")):
            for name, value in (given or {}).items():
                slot = group.get(name)
                if slot is None:
                    known = ", ".join(group) or "none"
                    other = self.inputs if what == "param" else self.params
                    hint = (
                        f" (`{name}` is {'an input' if what == 'param' else 'a param'}: pass it "
                        f"in {'inputs' if what == 'param' else 'params'}=)"
                        if name in other
                        else ""
                    )
                    raise ParamError(
                        f"the script has no {what} `{name}`{hint}; its {what}s: {known}"
                    )
                if hasattr(value, "detach"):  # a torch tensor
                    value = value.detach().cpu().numpy()
                given = np.asarray(value, dtype=object)
                # Every entry checked: True is not 1 Pa, None is not NaN, and strings (also
                # in a NumPy array) are read with their units.
                array = np.asarray(
                    [_number(name, v, slot.unit) for v in given.ravel()], dtype=np.float64
                ).reshape(given.shape)
                if array.size != 1 and array.shape != slot.shape:
                    raise ParamError(
                        f"`{name}` has shape {slot.shape}; a value of shape {array.shape} was "
                        f"given (give one value for every entry, or an array of shape {slot.shape})"
                    )
                out.append((name, array.ravel().tolist()))
        return out

    def _call(self, params, inputs, *, steps, dt, grad, checkpoint=None, memory_budget=None):
        text, loss, grads, state = self._native.run(
            self._values(params, inputs),
            steps=steps,
            dt=dt,
            grad=grad,
            checkpoint=checkpoint,
            memory_budget=memory_budget,
            keep_state=True,
        )
        if state is not None:
            x, v = state
            self._state = (
                np.asarray(x, dtype=np.float64).reshape(-1, 3),
                np.asarray(v, dtype=np.float64).reshape(-1, 3),
            )
        gradients = {name: _shaped(values, shape) for name, shape, values in grads}
        summary = json.loads(text)
        for message in summary.get("warnings", []):
            warnings.warn(message, SoftcWarning, stacklevel=3)
        return summary, loss, gradients

    def run(
        self,
        params: Optional[Mapping[str, Any]] = None,
        *,
        steps: Optional[int] = None,
        dt: Optional[float] = None,
        inputs: Optional[Mapping[str, Any]] = None,
        return_state: bool = False,
    ) -> dict:
        """Run the simulation with ``params`` (SI values by name, or strings with a unit such as
        ``"12 kPa"``; the others at the script's).

        Returns the summary ``softc run`` prints as JSON (loss, steps, dt, each node set's
        displacement, solver report…), bit-identical to ``softc run --no-optimize --set …``.
        ``steps`` and ``dt`` (seconds) override the script's. ``inputs`` sets the script's
        inputs (one scene); without it a script that lists several scenes runs each, and
        ``loss`` is their mean. ``return_state=True`` adds the final positions ``x`` and
        velocities ``v`` as ``(nodes, 3)`` arrays. Raises :class:`SimulationError`.
        """
        summary, _, _ = self._call(params, inputs, steps=steps, dt=dt, grad=False)
        if return_state:
            summary["x"], summary["v"] = self._state
        return summary

    def loss_and_grad(
        self,
        params: Optional[Mapping[str, Any]] = None,
        *,
        steps: Optional[int] = None,
        dt: Optional[float] = None,
        inputs: Optional[Mapping[str, Any]] = None,
        checkpoint: Optional[str] = None,
        memory_budget: Optional[str] = None,
    ) -> Tuple[float, Dict[str, Any]]:
        """The loss and d loss / d param for every param (a float, or an array of the param's
        shape), bit-identical to ``softc run --grad``.

        ``checkpoint``: ``"auto"``, ``"store_all"``, ``"periodic:K"`` or ``"revolve:N"``;
        ``memory_budget``: e.g. ``"512MB"`` (both override the script's optimize block). A script
        that lists several scenes of its inputs gives the mean loss and gradient over them.
        """
        summary, loss, gradients = self._call(
            params,
            inputs,
            steps=steps,
            dt=dt,
            grad=True,
            checkpoint=checkpoint,
            memory_budget=memory_budget,
        )
        self.last_summary = summary
        return loss, gradients

    def state(self) -> Tuple[np.ndarray, np.ndarray]:
        """The final positions and velocities ``(x, v)``, ``(nodes, 3)`` arrays in SI units, of
        the last run (its last scene)."""
        if self._state is None:
            raise RuntimeError("no run yet: call run() or loss_and_grad() first")
        return self._state
