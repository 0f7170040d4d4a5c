"""Test configuration: float64 on (references and finite differences need it)."""

import jax

jax.config.update("jax_enable_x64", True)
