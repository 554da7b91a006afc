"""Episode data: the Zarr episode store, frames for the models, and the formats policy
libraries read (LeRobot, HDF5, Diffusion Policy Zarr). Collection from the MuJoCo tasks is
the tasks' own tool, :mod:`iwsim.envs.collect`."""

from iwsim.data.store import EpisodeStore, StoreError

__all__ = ["EpisodeStore", "StoreError"]
