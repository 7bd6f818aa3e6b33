"""python -m edgecli: the `edge` command."""
import sys

from edgecli import main

sys.exit(main())
