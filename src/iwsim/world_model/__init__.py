"""The world model as one package: codecs, the dynamics behind a denoiser, the objectives,
the functional model (``StreamState`` + reset / step), its training and its presets.

    from iwsim.world_model import WorldModel
    wm = WorldModel.load("checkpoints/pusht-64")

- :mod:`.codecs`: the ``Codec`` interface (frames <-> latents, :mod:`.codecs.base`) and
  the codecs by kind: :mod:`.codecs.consistency` (the paper's consistency autoencoder),
  :mod:`.codecs.conv` (a deterministic convolutional autoencoder);
- :mod:`.dynamics`: the stage-2 network; :mod:`.denoiser`: the one calling convention
  training and inference share; :mod:`.objectives`: their losses and samplers;
- :mod:`.model`: :class:`WorldModel` and :class:`StreamState`;
- :mod:`.train_codec`, :mod:`.train_dynamics`, :mod:`.dynamics_data`: training;
- :mod:`.presets`: configs and named presets;
- :mod:`.env`: the Gymnasium envs over a world model (``iwsim/WorldModel-v0``, the vector env).
"""

from iwsim.world_model.codecs.base import Codec
from iwsim.world_model.model import KIND, StreamState, WorldModel, export_model

__all__ = ["KIND", "Codec", "StreamState", "WorldModel", "export_model"]
