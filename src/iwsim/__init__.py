"""iwsim: an interactive world simulator for robot learning."""

import iwsim.envs  # noqa: F401  (registers the Gymnasium ids)

__version__ = "0.1.0"


def __getattr__(name: str):
    # iwsim.WorldModel without importing torch on `import iwsim`
    if name == "WorldModel":
        from iwsim.world_model import WorldModel

        return WorldModel
    raise AttributeError(f"module 'iwsim' has no attribute {name!r}")
