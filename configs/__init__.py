# The Hydra configs, installed as the package spoil_torchrl.configs (see recipes/__init__.py).
