"""``python -m ogmapping.cli``: the ``ogmap`` command."""

import sys

from ogmapping.cli.commands import main

sys.exit(main())
