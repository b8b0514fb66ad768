"""``python -m tcn_ahrs.bench [key=value ...]`` (and the training worker subprocess)."""
import sys

from . import main
from .training import speed_worker

if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--train-worker":
        speed_worker(sys.argv[2])
    else:
        from omegaconf import OmegaConf

        main(OmegaConf.to_container(OmegaConf.from_dotlist(sys.argv[1:]), resolve=True))
