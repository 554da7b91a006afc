"""iwsim: an interactive world simulator for robot learning."""

import iwsim.envs  # noqa: F401  (registers the Gymnasium ids)

__version__ = "0.1.0"
