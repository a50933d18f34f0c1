"""``python -m s3k.cli``: the same as the ``s3k`` command."""

import sys

from s3k.cli import main

sys.exit(main())
