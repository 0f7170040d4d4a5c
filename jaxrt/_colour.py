"""colour-science, imported on first use (it is slow to import)."""

import functools
import warnings


@functools.cache
def colour():
    """The `colour` module, without its start-up warning about optional matplotlib."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Matplotlib.*")
        import colour
    return colour
