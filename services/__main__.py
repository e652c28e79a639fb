"""``python -m services`` is the ``handkse`` command."""

import sys

from services.cli import main

sys.exit(main())
