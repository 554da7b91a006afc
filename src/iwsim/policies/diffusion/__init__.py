"""Diffusion Policy (``dp``): :mod:`.config` (registered on import), :mod:`.model` (the network)."""

from iwsim.policies.diffusion import config  # noqa: F401  (registers the policy)
