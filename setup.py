"""The package layout pyproject.toml cannot say alone: ``conf/`` (the commands' configs, at the
repository's top where users read and edit them, as lightning-hydra-template keeps ``configs/``)
is installed as the package ``tcn_ahrs.conf``, so an installed wheel finds the same files
(Hydra's search path ``pkg://tcn_ahrs.conf``); ``checkpoints/`` likewise as ``tcn_ahrs.checkpoints``
(the shipped models, run by name from anywhere). Everything else is in pyproject.toml."""
from setuptools import find_packages, setup

setup(packages=find_packages(include=["tcn_ahrs*"]) + ["tcn_ahrs.conf", "tcn_ahrs.checkpoints"],
      package_dir={"tcn_ahrs.conf": "conf", "tcn_ahrs.checkpoints": "checkpoints"})
