"""``python -m groundstation`` is the same as the ``fasthex`` command."""

import sys

from groundstation.cli import main

sys.exit(main())
