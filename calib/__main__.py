"""``python -m calib``."""

from .cli import main

main()
