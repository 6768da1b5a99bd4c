"""`python -m quekaro` runs the command line (Ctrl-C while it imports: exit status 130, no traceback)."""

import sys

try:
    from quekaro.cli import main
except KeyboardInterrupt:
    sys.exit(130)

sys.exit(main())
