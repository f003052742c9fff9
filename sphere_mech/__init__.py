"""sphere_mech: global Lagrangian and Hamiltonian mechanics on (S^2)^n, derived by
autodiff from a user's L or H and integrated with diffrax on the spheres."""

import ast
import importlib
import importlib.metadata
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the public names; imported on first use (see `__getattr__`)
    from ._animation import animate as animate
    from ._batch import simulate_batch as simulate_batch
    from ._checks import unit_tolerance as unit_tolerance
    from ._fit.fit import FitResult as FitResult, fit as fit
    from ._fit.learn import (
        LearnedLagrangian as LearnedLagrangian,
        LearnResult as LearnResult,
        SphereKernels as SphereKernels,
        estimate_accelerations as estimate_accelerations,
        fit_accelerations as fit_accelerations,
        learn as learn,
        refine as refine,
    )
    from ._geometry import (
        constraint_error as constraint_error,
        hat as hat,
        nearest_rotation as nearest_rotation,
        normalize as normalize,
        project as project,
        random_points as random_points,
        random_state as random_state,
        retract as retract,
        rotate as rotate,
        rotation_matrix as rotation_matrix,
        sphere_exp as sphere_exp,
        tangent_basis as tangent_basis,
        vee as vee,
    )
    from ._hamiltonian import AngularHamiltonian as AngularHamiltonian, Hamiltonian as Hamiltonian
    from ._inertia import (
        AbstractConstantInertiaLagrangian as AbstractConstantInertiaLagrangian,
        ConstantInertiaLagrangian as ConstantInertiaLagrangian,
    )
    from ._lagrangian import AngularLagrangian as AngularLagrangian, Lagrangian as Lagrangian
    from ._legendre import (
        angular as angular,
        legendre as legendre,
        mu_from_pi as mu_from_pi,
        omega_from_qdot as omega_from_qdot,
        pi_from_mu as pi_from_mu,
        qdot_from_omega as qdot_from_omega,
    )
    from ._report import (
        SceneResult as SceneResult,
        run_scene as run_scene,
        work_energy_balance as work_energy_balance,
    )
    from ._results import RESULTS as RESULTS
    from ._scene.base import (
        AbstractDrive as AbstractDrive,
        AbstractEffect as AbstractEffect,
        AbstractForce as AbstractForce,
        AbstractKinetic as AbstractKinetic,
        AbstractPotential as AbstractPotential,
    )
    from ._scene.forces import (
        BaseForce as BaseForce,
        BaseTorque as BaseTorque,
        BodyTorque as BodyTorque,
        Harmonic as Harmonic,
        JointDamping as JointDamping,
        PDPosition as PDPosition,
        PDTorque as PDTorque,
        TipForce as TipForce,
        VibratingSupport as VibratingSupport,
    )
    from ._scene.kinetic import (
        Base as Base,
        Chain as Chain,
        Particles as Particles,
        RigidBase as RigidBase,
        SharedSphere as SharedSphere,
    )
    from ._scene.potentials import (
        Bending as Bending,
        Gravity as Gravity,
        PairInteraction as PairInteraction,
        Spring as Spring,
    )
    from ._scene.rotorcraft import (
        AbstractCommand as AbstractCommand,
        Circle as Circle,
        GeometricControl as GeometricControl,
        Hover as Hover,
        Line as Line,
        Rotors as Rotors,
        mixing_matrix as mixing_matrix,
    )
    from ._scene.scene import Scene as Scene, chain_pendulum as chain_pendulum
    from ._scene_files import (
        SceneFileError as SceneFileError,
        SceneSpec as SceneSpec,
        load_scene as load_scene,
    )
    from ._simulate import simulate as simulate
    from ._solve import (
        DEFAULT_MAX_STEPS as DEFAULT_MAX_STEPS,
        DEFAULT_TOLERANCES as DEFAULT_TOLERANCES,
        default_solver as default_solver,
    )
    from ._solvers.liegroup import LieRK as LieRK, LieRK4 as LieRK4
    from ._solvers.projected import Projected as Projected
    from ._solvers.rk4 import RK4 as RK4
    from ._solvers.variational import Variational as Variational
    from ._spaces import (
        Euclidean as Euclidean,
        Rotations as Rotations,
        Spheres as Spheres,
        chain_space as chain_space,
    )
    from ._system import (
        AbstractHamiltonianSystem as AbstractHamiltonianSystem,
        AbstractLagrangianSystem as AbstractLagrangianSystem,
        AbstractSystem as AbstractSystem,
    )
    from ._term import MechanicsTerm as MechanicsTerm


def _public_names() -> dict[str, str]:
    """Each public name and its module, read (not run) from the imports above: `import
    sphere_mech` stays cheap (`sphere-mech run` starts before diffrax is imported)."""
    tree = ast.parse(Path(__file__).read_text(encoding="utf-8"))
    block = next(node for node in tree.body if isinstance(node, ast.If))
    return {alias.asname: node.module for node in block.body for alias in node.names}


_PUBLIC = _public_names()


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))


__version__ = importlib.metadata.version("sphere_mech")

# What `from sphere_mech import *` gives and docs/api.md documents (tests/test_docs.py).
__all__ = sorted(_PUBLIC)
