"""Put a plant's remote state behind a link: the Gymnasium wrapper every policy runs through."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from codesign_mb.network.link import Link, Reception
from codesign_mb.network.qos import QosCost, QosPolicy, QosRequest, reliability_cost

__all__ = ["LinkObservationWrapper", "NetworkedPlant"]


@runtime_checkable
class NetworkedPlant(Protocol):
    """What a plant env declares so its remote state can be sent over a link.

    ``remote_slice`` selects the part of the (flat ``Box``) observation that is perceived at
    the edge and reaches the robot over the network; the rest (proprioception) is local and
    always fresh. ``remote_prior()`` is what the robot knows of the remote part before any
    delivery (e.g. the nominal spawn point of the object).
    """

    remote_slice: slice

    def remote_prior(self) -> NDArray[np.float64]: ...


class LinkObservationWrapper(gym.Wrapper):
    """Replace the remote part of the observation by ``y_t`` (``eq_output``), append ``zeta_t``.

    At every step the QoS policy picks ``(q_t, tau_t)`` from ``(y_{t-1}, zeta_{t-1})``
    (``eq_q_pol``), the plant's remote state ``x_t`` is sent over ``link`` with it, and the
    observation returned holds what the link delivered. ``info`` records the request, its
    cost ``C(q, tau)``, the delivery ``delta_t``, the age and the true remote state.

    Edge perception: when the plant's ``info["perceived"]`` is False (a missed detection, no
    object in view) there is no state to send: the network is asked nothing, the link is
    stepped with ``q = 0`` (nothing is delivered, what is held ages) and ``info`` records the
    request made, ``q = 0`` and its cost (the policy's own choice is ``info["qos_asked"]``):
    a packet that does not exist costs no radio resource, whichever the policy. The plant may
    give the true remote state as ``info["remote_true"]`` (when its remote part is perceived
    with errors); otherwise the remote part of its observation is the truth.

    A policy with ``reads_robot_state = True`` is given, instead of the remote part alone, the
    whole observation the robot held at ``t - 1`` (its proprioception, fresh, and ``y_{t-1}``):
    the paper's ``y_{t-1}`` when the robot's own state also counts as output (``eq_q_pol``).

    Seeding: ``reset(seed=s)`` seeds the env with ``s`` and the link and QoS policy with
    independent streams spawned from ``s``; ``reset()`` without a seed continues all streams.
    """

    def __init__(
        self,
        env: gym.Env,
        link: Link,
        qos_policy: QosPolicy,
        qos_cost: QosCost = reliability_cost,
    ) -> None:
        super().__init__(env)
        plant = env.unwrapped
        if not isinstance(plant, NetworkedPlant):
            raise TypeError(
                f"{type(plant).__name__} does not declare remote_slice and remote_prior()"
            )
        space = env.observation_space
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise TypeError("LinkObservationWrapper needs a flat Box observation space")
        self.link = link
        self.qos_policy = qos_policy
        self.qos_cost = qos_cost
        self.plant: NetworkedPlant = plant
        self.remote_slice: slice = plant.remote_slice
        horizon = getattr(plant, "horizon", None)
        age_high = np.inf if horizon is None else float(horizon) + 1.0
        self.observation_space = gym.spaces.Box(
            low=np.append(space.low, 0.0).astype(space.dtype),
            high=np.append(space.high, age_high).astype(space.dtype),
            dtype=space.dtype,
        )
        self._last: Reception | None = None
        self._held_full = np.zeros(space.shape[0])

    @property
    def last_reception(self) -> Reception | None:
        """What the link held after the last step."""
        return self._last

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        link_seed = qos_seed = None
        if seed is not None:
            link_ss, qos_ss = np.random.SeedSequence(seed).spawn(2)
            link_seed = int(link_ss.generate_state(1)[0])
            qos_seed = int(qos_ss.generate_state(1)[0])
        prior = np.asarray(self.plant.remote_prior(), dtype=np.float64)
        self._held_full = np.array(obs, dtype=np.float64, copy=True)
        self._held_full[self.remote_slice] = prior
        self.link.reset(seed=link_seed, prior=prior)
        self.qos_policy.reset(seed=qos_seed)
        # Before t = 0 the robot holds the prior, of age 0 by the convention of eq_time.
        return self._transmit(obs, info, prior, 0)

    def step(self, action: NDArray) -> tuple[NDArray, float, bool, bool, dict[str, Any]]:
        if self._last is None:
            raise RuntimeError("call reset() before step()")
        obs, reward, terminated, truncated, info = self.env.step(action)
        out, info = self._transmit(obs, info, self._last.observation, self._last.age)
        return out, float(reward), terminated, truncated, info

    def _transmit(
        self,
        obs: NDArray,
        info: dict[str, Any],
        held: NDArray[np.float64],
        age: int,
    ) -> tuple[NDArray, dict[str, Any]]:
        reads_robot_state = getattr(self.qos_policy, "reads_robot_state", False)
        seen = self._held_full if reads_robot_state else held
        asked = self.qos_policy.request(seen, age)  # eq_q_pol, eq_t_pol
        if not isinstance(asked, QosRequest):
            raise TypeError(f"qos_policy.request must return a QosRequest, got {asked!r}")
        remote = np.asarray(obs[self.remote_slice], dtype=float)
        sent = info.get("perceived", True)
        qos = asked if sent else QosRequest(0.0, asked.latency_steps)
        rx = self.link.step(remote, qos)
        self._last = rx
        out = np.empty(len(obs) + 1, dtype=self.observation_space.dtype)
        out[:-1] = obs
        out[self.remote_slice] = rx.observation  # eq_output
        out[-1] = rx.age
        if reads_robot_state:  # what the robot holds now, for the next request
            self._held_full = np.array(out[:-1], dtype=np.float64)
        info = dict(info)
        info.update(
            qos_reliability=qos.reliability,
            qos_asked=asked.reliability,
            qos_latency_steps=qos.latency_steps,
            qos_cost=float(self.qos_cost(qos)),
            delivered=rx.delivered,
            age=rx.age,
            remote_true=remote if info.get("remote_true") is None else info["remote_true"],
        )
        return out, info
