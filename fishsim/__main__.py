"""``python -m fishsim ...`` (and ``torchrun -m fishsim train-hydronet ...``): the CLI."""

from fishsim.cli import main

main()
