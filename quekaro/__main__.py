"""`python -m quekaro` runs the command line."""

import sys

from quekaro.cli import main

sys.exit(main())
