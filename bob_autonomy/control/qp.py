"""The casadi QP plumbing the MPCs share (bob_autonomy.control.mpc, bob_autonomy.control.motorboat_control): the
conic plugins and their options, a Function called through preallocated buffers, the solve errors with the
CPU-time budget check, and the inputs made finite (a non-finite entry counts as 0 or a default)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import casadi as ca
import numpy as np

from bob_autonomy.core.arrays import FloatArray

# casadi conic plugins in the order of their measured cost on this problem (cheapest first); proxqp and
# qrqp are left out (wrong or failed solves on random instances, see the docstring of bob_autonomy.control.mpc).
QP_PLUGINS = ("daqp", "qpoases", "osqp")

_PLUGIN_OPTIONS: dict[str, dict[str, object]] = {
    "daqp": {},
    "qpoases": {"printLevel": "none", "sparse": False},
    "osqp": {
        "osqp": {"verbose": False, "eps_abs": 1e-7, "eps_rel": 1e-7, "polish": False},
        "warm_start_primal": True,
        "warm_start_dual": True,
    },
    "proxqp": {},
    "qrqp": {"print_iter": False, "print_header": False, "print_info": False},
}


def default_qp_plugin() -> str:
    """The cheapest casadi QP plugin available in this installation (see QP_PLUGINS)."""
    for plugin in QP_PLUGINS:
        if ca.has_conic(plugin):
            return plugin
    raise RuntimeError(f"none of the casadi QP plugins {QP_PLUGINS} is available")


class _SolveError(RuntimeError):
    """The solver returned without an optimal solution, or too late, or a non-finite one."""


def _over_budget(elapsed_s: float, budget_s: float, what: str = "") -> str:
    return f"over the time budget ({elapsed_s * 1e3:.2f} ms{what} > {budget_s * 1e3:.2f} ms)"


def _cpu_over_budget(cpu_s: float, budget_s: float) -> None:
    """Raise _SolveError when a solve used more than budget_s of its thread's CPU time (s)."""
    if cpu_s > budget_s:
        raise _SolveError(_over_budget(cpu_s, budget_s, " of CPU"))


class _BufferedCall:
    """A casadi Function evaluated through Function.buffer on preallocated numpy arrays.

    inputs / outputs: name -> float64 array of the nonzeros (column-major), alive
    as long as this object. `shared` arrays (e.g. another function's outputs)
    are bound as inputs of the same name, so one function writes into the next.
    """

    def __init__(
        self, function: ca.Function, shared: dict[str, FloatArray] | None = None, failure_label: str | None = None
    ) -> None:
        self.function = function
        self.failure_label = failure_label or function.name()
        self.buffer, self._evaluate = function.buffer()
        self.inputs: dict[str, FloatArray] = {}
        self.outputs: dict[str, FloatArray] = {}
        for i, name in enumerate(function.name_in()):
            array = shared[name] if shared and name in shared else np.zeros(function.nnz_in(i))
            if array.size:
                self.buffer.set_arg(i, memoryview(array))
            self.inputs[name] = array
        for i, name in enumerate(function.name_out()):
            array = np.zeros(function.nnz_out(i))
            if array.size:
                self.buffer.set_res(i, memoryview(array))
            self.outputs[name] = array

    def __call__(self) -> None:
        try:
            self._evaluate()
        except RuntimeError:  # a conic solver (built with error_on_fail) did not solve: say its status
            raise _SolveError(f"{self.failure_label}: {self.buffer.stats().get('return_status')}") from None
        if self.buffer.ret() != 0:
            raise _SolveError(f"{self.function.name()} returned {self.buffer.ret()}")

    def stats(self) -> dict[str, object]:
        return self.buffer.stats()


def share_one_mapped_call(controllers: Sequence[Any], kind: type, shared: Callable[[Any], tuple]) -> bool:
    """Whether `controllers` can be solved in one mapped call (bob_autonomy.control.buoy_mpc_batch,
    motorboat_mpc_batch): two or more `kind` controllers using DAQP without a CPU-time budget (simulated time: a
    budget is per solve), whose `shared(c)` agree (casadi Functions by identity, anything else by value)."""
    if len(controllers) < 2 or not all(isinstance(c, kind) for c in controllers):
        return False
    first = shared(controllers[0])
    return all(
        c.solver == "daqp"
        and math.isinf(c.time_budget_s)
        and all(
            (mine is theirs) if isinstance(theirs, ca.Function) else mine == theirs
            for mine, theirs in zip(shared(c), first, strict=True)
        )
        for c in controllers
    )


def _conic(name: str, plugin: str, hessian: ca.Sparsity, constraints: ca.Sparsity) -> ca.Function:
    """A conic QP solver that raises when it does not solve (error_on_fail), so a solve is checked without
    FunctionBuffer.stats(), which costs about ten times the solve of these small QPs."""
    options: dict[str, object] = {"error_on_fail": True, **_PLUGIN_OPTIONS.get(plugin, {})}
    return ca.conic(name, plugin, {"h": hessian, "a": constraints}, options)


Pair = tuple[float, float]


def _pair(value: object) -> Pair:
    """The two entries of a (2,) vector as floats, non-finite ones replaced by 0."""
    array = np.asarray(value, dtype=float).reshape(2)
    x, y = float(array[0]), float(array[1])
    return (x if math.isfinite(x) else 0.0, y if math.isfinite(y) else 0.0)


def _vector2(value: object) -> FloatArray:
    """A float (2,) copy of value with non-finite entries replaced by 0."""
    return np.array(_pair(value))


def _finite_float(value: object, default: float) -> float:
    """value as a float, or default when it is not finite."""
    number = float(value)  # type: ignore[arg-type]
    return number if math.isfinite(number) else default
