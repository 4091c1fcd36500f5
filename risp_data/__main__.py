"""``python -m risp_data`` = ``risp-data``."""

from .cli import main

main()
