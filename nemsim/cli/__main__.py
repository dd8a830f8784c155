"""``python -m nemsim.cli ARGS``: the command line without the console script's allocator re-execution (which
re-executes into this), e.g. under ``torchrun -m nemsim.cli train ARGS``."""

import sys

from nemsim.cli import exit_process, main

sys.exit(exit_process(main()))
