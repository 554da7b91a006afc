"""Episode data: the Zarr episode store and collection from the MuJoCo tasks."""

from iwsim.data.store import EpisodeStore, StoreError

__all__ = ["EpisodeStore", "StoreError"]
