"""Plants: linear plants (python-control) and the MuJoCo conveyor pick-and-place env."""

import gymnasium as _gym

# The conveyor env (part ROBOT); the entry point is a string so that importing this package
# does not import MuJoCo.
if "codesign_mb/ConveyorPickPlace-v0" not in _gym.registry:
    _gym.register(
        id="codesign_mb/ConveyorPickPlace-v0",
        entry_point="codesign_mb.plants.conveyor:ConveyorPickPlace",
    )
