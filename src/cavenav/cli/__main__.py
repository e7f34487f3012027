"""`python -m cavenav.cli`."""

from cavenav.cli import main

main()
