"""`python -m jaxrt ...` runs the `jaxrt` command line (`jaxrt.cli`)."""

from .cli import run

run()
