"""``python -m risp_tasks …`` = ``risp-task …``."""

from risp_tasks.cli import main

main()
