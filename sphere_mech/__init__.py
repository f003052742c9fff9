"""sphere_mech: global Lagrangian and Hamiltonian mechanics on (S^2)^n, derived by
autodiff from a user's L or H and integrated with diffrax on the spheres."""

from ._batch import simulate_batch as simulate_batch
from ._chain import ChainPendulum as ChainPendulum
from ._chain import chain_pendulum as chain_pendulum
from ._checks import unit_tolerance as unit_tolerance
from ._convert import (
    angular as angular,
)
from ._convert import (
    legendre as legendre,
)
from ._convert import (
    mu_from_pi as mu_from_pi,
)
from ._convert import (
    omega_from_qdot as omega_from_qdot,
)
from ._convert import (
    pi_from_mu as pi_from_mu,
)
from ._convert import (
    qdot_from_omega as qdot_from_omega,
)
from ._fit.fit import FitResult as FitResult
from ._fit.fit import fit as fit
from ._geometry import (
    constraint_error as constraint_error,
)
from ._geometry import (
    hat as hat,
)
from ._geometry import (
    normalize as normalize,
)
from ._geometry import (
    project as project,
)
from ._geometry import (
    random_points as random_points,
)
from ._geometry import (
    random_state as random_state,
)
from ._geometry import (
    retract as retract,
)
from ._geometry import (
    rotate as rotate,
)
from ._geometry import (
    rotation_matrix as rotation_matrix,
)
from ._geometry import (
    sphere_exp as sphere_exp,
)
from ._geometry import (
    tangent_basis as tangent_basis,
)
from ._hamiltonian import AngularHamiltonian as AngularHamiltonian
from ._hamiltonian import Hamiltonian as Hamiltonian
from ._inertia import (
    AbstractConstantInertiaLagrangian as AbstractConstantInertiaLagrangian,
)
from ._inertia import (
    ConstantInertiaLagrangian as ConstantInertiaLagrangian,
)
from ._lagrangian import (
    AbstractLagrangianSystem as AbstractLagrangianSystem,
)
from ._lagrangian import (
    AngularLagrangian as AngularLagrangian,
)
from ._lagrangian import (
    Lagrangian as Lagrangian,
)
from ._scene.base import (
    AbstractEffect as AbstractEffect,
)
from ._scene.base import (
    AbstractForce as AbstractForce,
)
from ._scene.base import (
    AbstractKinetic as AbstractKinetic,
)
from ._scene.base import (
    AbstractPotential as AbstractPotential,
)
from ._scene.files import (
    SceneFileError as SceneFileError,
)
from ._scene.files import (
    SceneSpec as SceneSpec,
)
from ._scene.files import (
    load_scene as load_scene,
)
from ._scene.forces import (
    BaseTorque as BaseTorque,
)
from ._scene.forces import (
    JointDamping as JointDamping,
)
from ._scene.forces import (
    PDTorque as PDTorque,
)
from ._scene.forces import (
    TipForce as TipForce,
)
from ._scene.forces import (
    VibratingSupport as VibratingSupport,
)
from ._scene.kinetic import (
    Chain as Chain,
)
from ._scene.kinetic import (
    Particles as Particles,
)
from ._scene.kinetic import (
    SharedSphere as SharedSphere,
)
from ._scene.potentials import (
    Bending as Bending,
)
from ._scene.potentials import (
    Gravity as Gravity,
)
from ._scene.potentials import (
    PairInteraction as PairInteraction,
)
from ._scene.potentials import (
    Spring as Spring,
)
from ._scene.report import (
    SceneResult as SceneResult,
)
from ._scene.report import (
    run_scene as run_scene,
)
from ._scene.report import (
    work_energy_balance as work_energy_balance,
)
from ._scene.scene import Scene as Scene
from ._simulate import (
    DEFAULT_MAX_STEPS as DEFAULT_MAX_STEPS,
)
from ._simulate import (
    DEFAULT_TOLERANCES as DEFAULT_TOLERANCES,
)
from ._simulate import (
    default_solver as default_solver,
)
from ._simulate import (
    simulate as simulate,
)
from ._solvers.liegroup import LieRK4 as LieRK4
from ._solvers.projected import Projected as Projected
from ._solvers.rk4 import RK4 as RK4
from ._solvers.variational import Variational as Variational
from ._system import AbstractSystem as AbstractSystem

__version__ = "0.1.0"
