"""``python -m lmpromp_ppl.cli``: the ``lmpromp`` command without the console script."""

import sys

from lmpromp_ppl.cli import main

sys.exit(main())
