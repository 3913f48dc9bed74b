"""Linear plants for analysis: discrete-time ``StateSpace`` models and a Gymnasium env.

The plants are the linear-Gaussian instance of the paper's dynamics (``eq_control_orig``)::

    x_{t+1} = A x_t + B u_t + w_t,   w_t ~ N(0, W)
    z_t     = C x_t + v_t,           v_t ~ N(0, V)

sampled at the control period ``dt = 0.04 s``. The sensor measurement ``z_t`` is what the edge
sends over the link; the robot receives ``y_t = z_{t - zeta_t}`` (``eq_output``). A
:class:`LinearPlantSpec` is the frozen description of such a plant; :class:`LinearPlantEnv` is
the mutable workspace made from it (state, time, random stream) with the quadratic stage cost
``x' Q x + u' R u`` as negative reward.

The factories order the state so that the measured coordinates come first (``C = [I_p 0]``):
the first ``p`` entries of a state estimate then estimate the noise-free measurement, which is
what the rollout's ``estimation_error`` column compares with the true remote value.

Examples
--------
>>> plant = scalar_unstable(a=1.2)
>>> plant.system.isdtime(strict=True), plant.n_states
(True, 1)
>>> env = LinearPlantEnv(plant, horizon=10)
>>> z, info = env.reset(seed=0)
>>> z.shape, info["state"].shape
((1,), (1,))
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import control
import gymnasium as gym
import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from codesign_mb.core.config import as_matrix
from codesign_mb.core.registry import create, kinds

__all__ = [
    "CONTROL_PERIOD_S",
    "LinearPlantEnv",
    "LinearPlantSpec",
    "double_integrator",
    "inverted_pendulum",
    "make_linear_env",
    "make_linear_plant",
    "scalar_unstable",
]

CONTROL_PERIOD_S = 0.04
"""The control period of the toolkit (paper sec. 6: 40 ms), in seconds."""

FloatArray = NDArray[np.float64]


def _matrix(name: str, value: ArrayLike, shape: tuple[int, int] | None = None) -> FloatArray:
    """``value`` as a finite, read-only 2-D float array (scalars become 1 x 1)."""
    out = as_matrix(name, value, shape)
    out.setflags(write=False)
    return out


def _vector(name: str, value: ArrayLike, size: int) -> FloatArray:
    """``value`` as a finite, read-only 1-D float array of ``size`` entries."""
    try:
        out = np.array(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric vector, got {value!r}") from exc
    if out.shape != (size,):
        raise ValueError(f"{name} must have {size} entries, got {out.size}")
    if not np.isfinite(out).all():
        raise ValueError(f"{name} must be finite, got {out.tolist()}")
    out.setflags(write=False)
    return out


def _check_covariance(name: str, value: FloatArray, *, definite: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is symmetric positive (semi-)definite."""
    scale = max(1.0, float(np.max(np.abs(value))))
    if not np.allclose(value, value.T, rtol=0.0, atol=1e-10 * scale):
        raise ValueError(f"{name} must be symmetric, got {value.tolist()}")
    smallest = float(np.min(np.linalg.eigvalsh(value)))
    if smallest < -1e-10 * scale or (definite and smallest <= 0.0):
        kind = "positive definite" if definite else "positive semidefinite"
        raise ValueError(f"{name} must be {kind}, its smallest eigenvalue is {smallest:.3g}")


def _psd_sqrt(value: FloatArray) -> FloatArray:
    """A factor ``L`` with ``L L' = value`` that also works for singular covariances."""
    eigval, eigvec = np.linalg.eigh(value)
    return eigvec * np.sqrt(np.clip(eigval, 0.0, None))


@dataclass(frozen=True, eq=False)
class LinearPlantSpec:
    """A discrete-time linear-Gaussian plant: the frozen description, no state.

    ``x_{t+1} = A x_t + B u_t + w_t`` with ``w_t ~ N(0, W)`` (``eq_control_orig``) and the
    sensor measurement ``z_t = C x_t + v_t`` with ``v_t ~ N(0, V)``.

    Parameters
    ----------
    name:
        A short label (used in tables and plots).
    A:
        State matrix, shape ``(n, n)``.
    B:
        Input matrix, shape ``(n, m)``.
    C:
        Measurement matrix, shape ``(p, n)``.
    W:
        Process-noise covariance, shape ``(n, n)``, symmetric positive semidefinite.
    V:
        Measurement-noise covariance, shape ``(p, p)``, symmetric positive semidefinite.
    dt:
        Sampling period in seconds (> 0); the toolkit's control period is 0.04 s.

    Raises
    ------
    ValueError
        On a non-finite entry, a mismatched shape or an invalid covariance; the message names
        the field, e.g. ``"W must have shape (2, 2), got (3, 3)"``.
    """

    name: str
    A: FloatArray
    B: FloatArray
    C: FloatArray
    W: FloatArray
    V: FloatArray
    dt: float = CONTROL_PERIOD_S

    def __post_init__(self) -> None:
        A = _matrix("A", self.A)
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"A must be square, got shape {A.shape}")
        B = _matrix("B", self.B)
        if B.shape[0] != n:
            raise ValueError(f"B must have {n} rows to match A, got shape {B.shape}")
        C = _matrix("C", self.C)
        if C.shape[1] != n:
            raise ValueError(f"C must have {n} columns to match A, got shape {C.shape}")
        p = C.shape[0]
        W = _matrix("W", self.W)
        if W.shape != (n, n):
            raise ValueError(f"W must have shape {(n, n)} to match A, got {W.shape}")
        V = _matrix("V", self.V)
        if V.shape != (p, p):
            raise ValueError(f"V must have shape {(p, p)} to match C, got {V.shape}")
        _check_covariance("W", W)
        _check_covariance("V", V)
        dt = float(self.dt)
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt must be a positive number of seconds, got {self.dt!r}")
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty string, got {self.name!r}")
        for key, value in (("A", A), ("B", B), ("C", C), ("W", W), ("V", V), ("dt", dt)):
            object.__setattr__(self, key, value)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LinearPlantSpec):
            return NotImplemented
        return (
            self.name == other.name
            and self.dt == other.dt
            and all(
                np.array_equal(getattr(self, k), getattr(other, k))
                for k in ("A", "B", "C", "W", "V")
            )
        )

    def __hash__(self) -> int:
        return hash(
            (self.name, self.dt, *(getattr(self, k).tobytes() for k in ("A", "B", "C", "W", "V")))
        )

    @classmethod
    def from_system(
        cls, system: control.StateSpace, W: ArrayLike, V: ArrayLike, *, name: str
    ) -> LinearPlantSpec:
        """The spec of a discrete-time, strictly proper python-control ``StateSpace``."""
        if not system.isdtime(strict=True) or system.dt is True:
            raise ValueError(f"system must be discrete-time with a numeric dt, got dt={system.dt}")
        if np.any(np.asarray(system.D) != 0.0):
            raise ValueError("system must be strictly proper (D = 0)")
        return cls(name=name, A=system.A, B=system.B, C=system.C, W=W, V=V, dt=float(system.dt))

    @cached_property
    def system(self) -> control.StateSpace:
        """The plant as a discrete-time python-control ``StateSpace`` (``D = 0``)."""
        D = np.zeros((self.n_outputs, self.n_inputs))
        return control.ss(self.A, self.B, self.C, D, self.dt)

    @property
    def n_states(self) -> int:
        """State dimension ``n``."""
        return self.A.shape[0]

    @property
    def n_inputs(self) -> int:
        """Input dimension ``m``."""
        return self.B.shape[1]

    @property
    def n_outputs(self) -> int:
        """Measurement dimension ``p``."""
        return self.C.shape[0]

    @property
    def spectral_radius(self) -> float:
        """``max |lambda_i(A)|``: the open loop is unstable when it exceeds 1."""
        return float(np.max(np.abs(np.linalg.eigvals(self.A))))


def _van_loan(Ac: FloatArray, Qc: FloatArray, dt: float) -> FloatArray:
    """Covariance ``int_0^dt e^{Ac s} Qc e^{Ac' s} ds`` of continuous white noise over ``dt``."""
    n = Ac.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -Ac
    M[:n, n:] = Qc
    M[n:, n:] = Ac.T
    E = scipy.linalg.expm(M * dt)
    Ad = E[n:, n:].T
    Wd = Ad @ E[:n, n:]
    return 0.5 * (Wd + Wd.T)


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return value


def _non_negative(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value >= 0.0):
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return value


def scalar_unstable(
    a: float = 1.2,
    *,
    b: float = 1.0,
    w: float = 1.0,
    v: float = 1.0,
    dt: float = CONTROL_PERIOD_S,
) -> LinearPlantSpec:
    """The scalar plant ``x_{t+1} = a x_t + b u_t + w_t``, ``z_t = x_t + v_t``.

    With ``|a| > 1`` it is the plant of Sinopoli et al. (2004): the Kalman filter's expected
    error covariance stays bounded iff the arrival probability exceeds ``1 - 1/a^2``.

    Parameters
    ----------
    a:
        Discrete-time pole (per step of ``dt``).
    b:
        Input gain.
    w, v:
        Process and measurement noise variances (>= 0).
    dt:
        Sampling period in seconds.
    """
    for name, value in (("a", a), ("b", b)):
        if not math.isfinite(float(value)):
            raise ValueError(f"{name} must be finite, got {value!r}")
    system = control.ss([[a]], [[b]], [[1.0]], [[0.0]], _positive("dt", dt))
    return LinearPlantSpec.from_system(
        system, [[_non_negative("w", w)]], [[_non_negative("v", v)]], name=f"scalar(a={a:g})"
    )


def double_integrator(
    *,
    accel_noise_std: float = 1.0,
    position_noise_std: float = 0.01,
    dt: float = CONTROL_PERIOD_S,
) -> LinearPlantSpec:
    """A unit mass on a line: state ``(position m, velocity m/s)``, input force N.

    Sampled with a zero-order hold (``control.sample_system``); the process noise is a
    white acceleration of intensity ``accel_noise_std**2`` (m^2/s^3), discretised exactly
    (Van Loan); the position is measured with standard deviation ``position_noise_std`` (m).
    """
    Ac = np.array([[0.0, 1.0], [0.0, 0.0]])
    Bc = np.array([[0.0], [1.0]])
    C = np.array([[1.0, 0.0]])
    system = control.sample_system(
        control.ss(Ac, Bc, C, [[0.0]]), _positive("dt", dt), method="zoh"
    )
    sigma_a = _non_negative("accel_noise_std", accel_noise_std)
    W = _van_loan(Ac, Bc @ Bc.T * sigma_a**2, float(dt))
    V = [[_non_negative("position_noise_std", position_noise_std) ** 2]]
    return LinearPlantSpec.from_system(system, W, V, name="double_integrator")


def inverted_pendulum(
    *,
    cart_mass: float = 1.0,
    pole_mass: float = 0.1,
    pole_length: float = 0.5,
    gravity: float = 9.81,
    force_noise_std: float = 0.5,
    position_noise_std: float = 0.01,
    angle_noise_std: float = 0.01,
    dt: float = CONTROL_PERIOD_S,
) -> LinearPlantSpec:
    """A cart-pole linearised about the upright equilibrium.

    State ``(cart position m, pole angle rad, cart velocity m/s, pole rate rad/s)``, input the
    horizontal force on the cart (N); cart position and pole angle are measured. With a point
    mass ``m`` at distance ``l`` on a cart of mass ``M`` (no friction)::

        p'' = (u - m g theta) / M
        theta'' = ((M + m) g theta - u) / (M l)

    so the unstable pole is ``sqrt((M + m) g / (M l))`` rad/s, ``exp(4.65 * 0.04) = 1.20`` per
    step with the defaults. Sampled with a zero-order hold; the force disturbance is white of
    intensity ``force_noise_std**2`` (N^2 s), discretised exactly (Van Loan).
    """
    M = _positive("cart_mass", cart_mass)
    m = _positive("pole_mass", pole_mass)
    length = _positive("pole_length", pole_length)
    g = _positive("gravity", gravity)
    Ac = np.zeros((4, 4))
    Ac[0, 2] = Ac[1, 3] = 1.0
    Ac[2, 1] = -m * g / M
    Ac[3, 1] = (M + m) * g / (M * length)
    Bc = np.array([[0.0], [0.0], [1.0 / M], [-1.0 / (M * length)]])
    C = np.hstack([np.eye(2), np.zeros((2, 2))])
    system = control.sample_system(
        control.ss(Ac, Bc, C, np.zeros((2, 1))), _positive("dt", dt), method="zoh"
    )
    sigma_f = _non_negative("force_noise_std", force_noise_std)
    W = _van_loan(Ac, Bc @ Bc.T * sigma_f**2, float(dt))
    V = np.diag(
        [
            _non_negative("position_noise_std", position_noise_std) ** 2,
            _non_negative("angle_noise_std", angle_noise_std) ** 2,
        ]
    )
    return LinearPlantSpec.from_system(system, W, V, name="inverted_pendulum")


def make_linear_plant(name: str) -> LinearPlantSpec:
    """The plant registered as ``name`` (role ``linear_plant``), with default parameters."""
    if name not in kinds("linear_plant"):
        raise ValueError(
            f"plant must be one of {', '.join(sorted(kinds('linear_plant')))}, got {name!r}"
        )
    spec: LinearPlantSpec = create("linear_plant", name)
    return spec


def make_linear_env(plant: str = "pendulum", **options: Any) -> LinearPlantEnv:
    """The linear plant ``plant`` (a ``linear_plant`` kind) as an env (Gymnasium entry point).

    ``options`` are :class:`LinearPlantEnv`'s keyword arguments (``horizon``, ``x0_cov``, ...).
    """
    return LinearPlantEnv(make_linear_plant(plant), **options)


@dataclass(eq=False)
class _Workspace:
    """The mutable part of an episode."""

    x: FloatArray
    t: int = 0


class LinearPlantEnv(gym.Env[NDArray[np.float64], NDArray[np.float64]]):
    """A :class:`LinearPlantSpec` as a Gymnasium env whose measurement goes over the link.

    Observation: the measurement ``z_t = C x_t + v_t`` (shape ``(p,)``), all of it remote
    (``remote_slice``), i.e. sent over the network by a
    :class:`~codesign_mb.network.LinkObservationWrapper`. Action: ``u_t`` (shape ``(m,)``),
    clipped to ``[-action_bound, action_bound]``. Reward: ``-(x_t' Q x_t + u_t' R u_t)``, the
    stage cost of the state before the transition and the applied input. The episode is
    truncated after ``horizon`` steps and never terminates.

    Parameters
    ----------
    plant:
        The plant description.
    horizon:
        Episode length in steps (>= 1).
    state_cost:
        ``Q``, shape ``(n, n)``, symmetric positive semidefinite; identity by default.
    input_cost:
        ``R``, shape ``(m, m)``, symmetric positive definite; identity by default.
    x0_mean:
        Mean of the initial state, shape ``(n,)``; zeros by default.
    x0_cov:
        Covariance of the initial state, shape ``(n, n)``; identity by default.
    action_bound:
        Symmetric bound on every input entry (> 0, may be ``inf``).
    render_mode:
        Unused (no rendering); accepted for the Gymnasium constructor convention.

    Notes
    -----
    Randomness only through ``reset(seed=...)``: the env's own generator ``np_random`` draws
    ``x_0``, then per step ``w_t`` followed by ``v_{t+1}``. ``info`` carries the true state
    ``"state"`` (``x_t`` at reset, ``x_{t+1}`` after a step) and the ``"stage_cost"`` of the step.
    ``reset(options={"x0": ...})`` starts from a given state instead of sampling it.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 (Gymnasium convention)

    def __init__(
        self,
        plant: LinearPlantSpec,
        *,
        horizon: int = 250,
        state_cost: ArrayLike | None = None,
        input_cost: ArrayLike | None = None,
        x0_mean: ArrayLike | None = None,
        x0_cov: ArrayLike | None = None,
        action_bound: float = math.inf,
        render_mode: str | None = None,
    ) -> None:
        if not isinstance(plant, LinearPlantSpec):
            raise TypeError(f"plant must be a LinearPlantSpec, got {type(plant).__name__}")
        n, m, p = plant.n_states, plant.n_inputs, plant.n_outputs
        if isinstance(horizon, bool) or int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        Q = _matrix("state_cost", np.eye(n) if state_cost is None else state_cost, (n, n))
        R = _matrix("input_cost", np.eye(m) if input_cost is None else input_cost, (m, m))
        _check_covariance("state_cost", Q)
        _check_covariance("input_cost", R, definite=True)
        mean = _vector("x0_mean", np.zeros(n) if x0_mean is None else x0_mean, n)
        cov = _matrix("x0_cov", np.eye(n) if x0_cov is None else x0_cov, (n, n))
        _check_covariance("x0_cov", cov)
        bound = float(action_bound)
        if math.isnan(bound) or bound <= 0.0:
            raise ValueError(f"action_bound must be > 0, got {action_bound!r}")
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (no rendering), got {render_mode!r}")

        self.plant = plant
        self.horizon = int(horizon)
        self.state_cost = Q
        self.input_cost = R
        self.x0_mean = mean
        self.x0_cov = cov
        self.action_bound = bound
        self.render_mode = render_mode
        self.control_period_s = plant.dt
        self.remote_slice = slice(0, p)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(p,), dtype=np.float64)
        self.action_space = gym.spaces.Box(-bound, bound, shape=(m,), dtype=np.float64)
        self._w_sqrt = _psd_sqrt(plant.W)
        self._v_sqrt = _psd_sqrt(plant.V)
        self._x0_sqrt = _psd_sqrt(cov)
        self._ws: _Workspace | None = None

    @property
    def state(self) -> FloatArray:
        """A copy of the true state ``x_t``."""
        if self._ws is None:
            raise RuntimeError("call reset() before reading the state")
        return self._ws.x.copy()

    @property
    def t(self) -> int:
        """The current step (0 after reset)."""
        return 0 if self._ws is None else self._ws.t

    def remote_prior(self) -> FloatArray:
        """The prior mean measurement ``C E[x_0]``: what the robot holds before any delivery."""
        return self.plant.C @ self.x0_mean

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[FloatArray, dict[str, Any]]:
        super().reset(seed=seed)
        options = dict(options or {})
        x0 = options.pop("x0", None)
        if options:
            raise ValueError(f"unknown reset option(s) {sorted(options)}; expected 'x0'")
        if x0 is None:
            n = self.plant.n_states
            x = self.x0_mean + self._x0_sqrt @ self.np_random.standard_normal(n)
        else:
            x = np.array(_vector("x0", x0, self.plant.n_states))
        self._ws = _Workspace(x=x)
        return self._measure(x), {"state": x.copy()}

    def step(self, action: ArrayLike) -> tuple[FloatArray, float, bool, bool, dict[str, Any]]:
        if self._ws is None:
            raise RuntimeError("call reset() before step()")
        m = self.plant.n_inputs
        u = np.asarray(action, dtype=float).reshape(-1)
        if u.shape != (m,):
            raise ValueError(f"action must have {m} entries, got shape {np.shape(action)}")
        if math.isfinite(self.action_bound):
            u = np.clip(u, -self.action_bound, self.action_bound)
        x = self._ws.x
        stage_cost = float(x @ self.state_cost @ x + u @ self.input_cost @ u)
        w = self._w_sqrt @ self.np_random.standard_normal(self.plant.n_states)
        x_next = self.plant.A @ x + self.plant.B @ u + w  # eq_control_orig
        self._ws.x = x_next
        self._ws.t += 1
        z = self._measure(x_next)
        truncated = self._ws.t >= self.horizon
        info = {"state": x_next.copy(), "stage_cost": stage_cost}
        return z, -stage_cost, False, truncated, info

    def _measure(self, x: FloatArray) -> FloatArray:
        """The sensor measurement ``z = C x + v``."""
        v = self._v_sqrt @ self.np_random.standard_normal(self.plant.n_outputs)
        return self.plant.C @ x + v
