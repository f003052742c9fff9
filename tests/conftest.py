import os

import jax
import jax.random as jr
import pytest

jax.config.update("jax_enable_x64", True)
# How the suite compiles (few optimizations, every process): ../conftest.py.
# `sphere-mech run` in tests never touches the user's compilation cache (tests that check
# the cache give their own folder).
os.environ["SPHERE_MECH_CACHE_DIR"] = "off"


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs():
    """Drop JAX's compiled programs after each test file: a worker that keeps every
    program of the suite grew by about 1 GB a minute (two workers reached 10 GB of this
    24 GB machine, and XLA crashed compiling). Module fixtures share programs within a
    file, where the sharing is."""
    yield
    jax.clear_caches()


@pytest.fixture
def getkey():
    """A function returning a fresh PRNG key at each call (deterministic per test)."""
    state = {"key": jr.PRNGKey(5678)}

    def _getkey():
        state["key"], sub = jr.split(state["key"])
        return sub

    return _getkey
