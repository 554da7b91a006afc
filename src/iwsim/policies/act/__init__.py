"""ACT (``act``): :mod:`.config` (registered on import), :mod:`.model` (the network)."""

from iwsim.policies.act import config  # noqa: F401  (registers the policy)
