"""``python -m lensdist_torch.cli ...``: the ``lensdist`` command, as the console script runs it."""

import sys

from lensdist_torch.cli.commands import main

sys.exit(main())
