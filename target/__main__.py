"""``python -m fbgforce.target``: the target report of a model (default: a small one trained on
the ``smoke`` scene); exit status 1 unless bit-exact. See :func:`fbgforce.target.cli.main`."""
import sys

from fbgforce.target.cli import main

sys.exit(main())
