"""``python -m tcn_ahrs COMMAND ...`` = ``tcn-ahrs COMMAND ...``."""
from .cli import main

main()
