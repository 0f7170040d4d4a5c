"""`python -m jaxrt ...` runs the `jaxrt` command line (`jaxrt.cli`)."""

import sys

from .cli import main

sys.exit(main())
