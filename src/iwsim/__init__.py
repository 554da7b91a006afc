"""iwsim: an interactive world simulator for robot learning."""

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

# The Gymnasium ids, registered by name: gym.make imports each env's module when it is made
# (importing the tasks here would make the package root reach up into them).
for _id, _entry, _steps in (
    ("iwsim/BimanualPushT-v0", "iwsim.envs.pusht.sim:BimanualPushTEnv", 600),  # the paper's evaluation horizon
    ("iwsim/PileSweep-v0", "iwsim.envs.pilesweep.sim:PileSweepEnv", 200),  # the paper's pile-sweeping horizon
    ("iwsim/WorldModel-v0", "iwsim.world_model.env:WorldModelEnv", 600),
):
    if _id not in registry:
        register(id=_id, entry_point=_entry, max_episode_steps=_steps)
del _id, _entry, _steps  # the loop's names are not the package's


def __getattr__(name: str):
    # iwsim.WorldModel without importing torch on `import iwsim`
    if name == "WorldModel":
        from iwsim.world_model import WorldModel

        return WorldModel
    raise AttributeError(f"module 'iwsim' has no attribute {name!r}")
