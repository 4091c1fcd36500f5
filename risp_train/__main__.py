"""``python -m risp_train …`` (and ``torchrun --nproc-per-node N -m risp_train fit …``)."""

from .cli import main

if __name__ == "__main__":
    main()
