"""TEMPORARY (replaced by the scenes branch): chain_pendulum as a Scene."""

from ._scene.forces import BaseTorque, TipForce
from ._scene.kinetic import Chain
from ._scene.potentials import Gravity
from ._scene.scene import Scene


def chain_pendulum(masses, lengths, g=9.81, *, torque=None, tip_force=None):
    effects = [Chain(masses, lengths), Gravity(g)]
    if torque is not None:
        effects.append(BaseTorque(torque))
    if tip_force is not None:
        effects.append(TipForce(tip_force))
    return Scene(*effects)
