"""`python -m gscan.cli`: the `gscan` command."""
from gscan.cli import main

main()
