"""The world model as one package: codecs, the dynamics behind a denoiser, the objectives,
the functional model (``StreamState`` + reset / step), its training and its presets.

    from iwsim.world_model import WorldModel
    wm = WorldModel.load("checkpoints/pusht-64")

- :mod:`.codec`: the ``Codec`` interface (frames <-> latents) and the registry of codecs;
  :mod:`.autoencoder` (the paper's consistency autoencoder), :mod:`.conv_codec` (a
  deterministic convolutional autoencoder);
- :mod:`.dynamics`: the stage-2 network; :mod:`.denoiser`: the one calling convention
  training and inference share; :mod:`.objectives`: their losses and samplers;
- :mod:`.model`: :class:`WorldModel` and :class:`StreamState`;
- :mod:`.train_codec`, :mod:`.train_dynamics`, :mod:`.dynamics_data`: training;
- :mod:`.presets`: configs and named presets.
"""

from iwsim.world_model.codec import Codec
from iwsim.world_model.model import KIND, StreamState, WorldModel, export_model

__all__ = ["KIND", "Codec", "StreamState", "WorldModel", "export_model"]
