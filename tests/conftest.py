import os

import jax
import jax.random as jr
import pytest

jax.config.update("jax_enable_x64", True)
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
