import os

import jax
import jax.random as jr
import pytest

jax.config.update("jax_enable_x64", True)
# Most test time is XLA compiling many small programs that then run for milliseconds:
# compiling them with few optimizations cut the CPU time of the suite's heaviest files by
# 16-20 % (measured on test_forms, test_simulate + test_liegroup, test_fit). Only this
# process: the command line's subprocesses and the notebooks compile as users do.
jax.config.update("jax_disable_most_optimizations", True)
# `sphere-mech run` in tests never touches the user's compilation cache (tests that check
# the cache give their own folder).
os.environ["SPHERE_MECH_CACHE_DIR"] = "off"


@pytest.fixture
def getkey():
    """A function returning a fresh PRNG key at each call (deterministic per test)."""
    state = {"key": jr.PRNGKey(5678)}

    def _getkey():
        state["key"], sub = jr.split(state["key"])
        return sub

    return _getkey
