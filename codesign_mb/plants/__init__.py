"""Plants: linear plants (python-control), the MuJoCo conveyor pick-and-place, a kinematic toy,
and the belt-tracking double integrator of the linear sweep scenario.

The conveyor's named scenarios (``paper``, ``realistic``, ``variable``, ``constant-*``) are in
:mod:`codesign_mb.plants.scenarios`, its edge perception error models in
:mod:`codesign_mb.plants.perception`, why an episode failed in :mod:`codesign_mb.plants.outcomes`,
the phases of an episode (belt, grasp, carried) in :mod:`codesign_mb.plants.phases`.

Each is registered with Gymnasium, so ``gymnasium.make("codesign_mb/ConveyorPickPlace-v0")``
(or ``ToyConveyor-v0``, ``LinearPlant-v0`` with ``plant="pendulum"`` ...) gives it with its
spec. Entry points are strings: importing this package imports neither MuJoCo nor
python-control.
"""

import gymnasium as _gym

_ENVS = {
    "codesign_mb/ConveyorPickPlace-v0": "codesign_mb.plants.conveyor:ConveyorPickPlace",
    "codesign_mb/ToyConveyor-v0": "codesign_mb.plants.toy:ToyConveyor",
    "codesign_mb/LinearPlant-v0": "codesign_mb.plants.linear:make_linear_env",
    "codesign_mb/BeltTracking-v0": "codesign_mb.plants.belt_tracking:BeltTracking",
}

for _id, _entry_point in _ENVS.items():
    if _id not in _gym.registry:
        _gym.register(id=_id, entry_point=_entry_point)
