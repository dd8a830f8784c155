"""``torchrun --nproc-per-node N -m nemsim.train ARGS``: ``nemsim train ARGS`` in N processes (DDP)."""

import sys

from nemsim.cli import main

if __name__ == "__main__":
    sys.exit(main(["train", *sys.argv[1:]]))
