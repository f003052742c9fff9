"""`AbstractTransparentSolver`: a solver that wraps another and forwards everything that
describes the method (order, terms, interpolation, root finder, `isinstance` checks)."""

import abc

from diffrax import AbstractSolver, AbstractWrappedSolver


def _forwarded(name: str) -> property:
    """The wrapped solver's attribute `name`, read through the wrapper."""
    return property(lambda self: getattr(self.solver, name), doc=f"The wrapped solver's `{name}`.")


def described(solver) -> str:
    """How an error names the `solver` it was given: `the class Tsit5` for a class (a
    missing `()`), else its `repr`."""
    return f"the class {solver.__name__}" if isinstance(solver, type) else repr(solver)


class AbstractTransparentSolver(AbstractWrappedSolver):
    """Wraps `solver` (a field or property of the concrete class) and forwards its order,
    term structure, interpolation, root finder and scan kind, as diffrax's `HalfSolver`
    does; `isinstance` checks (adaptive, implicit) pass through to `solver` (diffrax's
    `AbstractWrappedSolver`, one level deep). Concrete wrappers say what they add in
    `init` and `step`."""

    def __check_init__(self):
        if not isinstance(self.solver, AbstractSolver):
            raise ValueError(
                f"{type(self).__name__}(solver): solver must be a diffrax solver "
                f"instance, e.g. diffrax.Tsit5() (got {described(self.solver)})"
            )

    # Read from the wrapped solver. `root_finder`, `root_find_max_steps`: diffrax reads
    # (and fills in) the tolerances of any solver that is an `AbstractImplicitSolver`,
    # which a wrapper of `Kvaerno5()` is by forwarding. `scan_kind`: `diffrax.ForwardMode`
    # reads it (and sets it to "lax" through it) so that forward mode works.
    term_structure = _forwarded("term_structure")
    interpolation_cls = _forwarded("interpolation_cls")
    term_compatible_contr_kwargs = _forwarded("term_compatible_contr_kwargs")
    root_finder = _forwarded("root_finder")
    root_find_max_steps = _forwarded("root_find_max_steps")
    scan_kind = _forwarded("scan_kind")

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    @abc.abstractmethod
    def init(self, terms, t0, t1, y0, args):
        """The solver state: the wrapped solver's, and what the wrapper adds."""

    @abc.abstractmethod
    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        """One step of the wrapped solver, and what the wrapper does with it."""

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


def unwrapped(solver):
    """The solver inside any `AbstractTransparentSolver`s around `solver` (they forward
    everything but their steps to it): what `isinstance` checks should see. (By type:
    diffrax's `isinstance` would look through any other wrapper, e.g. `HalfSolver`.)"""
    while issubclass(type(solver), AbstractTransparentSolver):
        solver = solver.solver
    return solver
