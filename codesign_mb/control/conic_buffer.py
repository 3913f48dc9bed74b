"""A ``casadi.conic`` QP solver called through its buffer: no per-call conversions.

``Function.call`` with a dict converts every numpy argument to a ``DM`` and every result back
(about 0.2 ms for the MPC's QP, more than qpOASES itself). CasADi's ``Function.buffer()``
evaluates the same solver, with the same memory (warm start), on arrays bound once:
:class:`ConicBuffer` binds one numpy array per input and output, and a call only runs the
solver. The solver, its options and its results are the ones of ``Function.call``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ConicBuffer"]


class ConicBuffer:
    """The inputs and outputs of a CasADi function as numpy arrays bound to its buffer.

    Parameters
    ----------
    function:
        A ``casadi.Function`` (here a ``casadi.conic``).
    fixed:
        Values of inputs set once (the constant Hessian and constraint matrix), as the
        nonzeros of the function's input sparsity (column-major for a dense matrix).

    Attributes
    ----------
    inputs, outputs:
        Name -> the bound array (write the inputs in place, read the outputs after a call).
    """

    def __init__(self, function: Any, fixed: Mapping[str, ArrayLike] | None = None) -> None:
        self.function = function
        self._buffer, self._eval = function.buffer()
        self.inputs: dict[str, NDArray[np.float64]] = {}
        self.outputs: dict[str, NDArray[np.float64]] = {}
        for i, name in enumerate(function.name_in()):
            array = np.zeros(function.nnz_in(i))
            self._buffer.set_arg(i, memoryview(array))
            self.inputs[name] = array
        for i, name in enumerate(function.name_out()):
            array = np.zeros(function.nnz_out(i))
            self._buffer.set_res(i, memoryview(array))
            self.outputs[name] = array
        for name, value in (fixed or {}).items():
            self.inputs[name][:] = np.asarray(value, dtype=float).ravel()

    def __call__(self) -> int:
        """Evaluate on the bound inputs; the return flag (0: success, e.g. a solved QP)."""
        self._eval()
        return int(self._buffer.ret())

    def stats(self) -> dict[str, Any]:
        """The solver statistics of the last call (``success``, ``return_status``, ...)."""
        return dict(self._buffer.stats())
