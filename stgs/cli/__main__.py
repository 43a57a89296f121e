"""`python -m stgs.cli COMMAND ...`, the same as the `stgs` script."""

import sys

from stgs.cli.commands import main

sys.exit(main())
