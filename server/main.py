"""`python -m stgs.server.main ROOT ...`: the server alone (the container entry point), same as `stgs serve`."""

import sys

from stgs.cli import main

if __name__ == "__main__":
    sys.exit(main(["serve", *sys.argv[1:]], commands=("serve",)))
