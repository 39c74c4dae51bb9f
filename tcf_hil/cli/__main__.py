"""``python -m tcf_hil.cli`` is the ``tcf-hil`` command."""

import sys

from tcf_hil.cli import main

sys.exit(main())
