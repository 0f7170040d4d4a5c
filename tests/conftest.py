"""Test configuration: float64 on (references and finite differences need it).

The persistent compilation cache stays off in tests (`JAXRT_NO_CACHE=1`, unless the
environment sets it): a test that runs the CLI in-process would otherwise turn JAX's
on-disk cache on for every later test of the session, and the tests that check caching
turn it on themselves, in a folder of their own.
"""

import os

os.environ.setdefault("JAXRT_NO_CACHE", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
