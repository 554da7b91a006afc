"""The yardstick's measures: what users do with a world model, measured in the model and in
MuJoCo from the same first states (``bench/yardstick.py`` runs them, one table row per
model; ``bench/pile_families.py``, ``bench/ablate_dynamics.py``, ``bench/wm_studies_check.py``
and ``bench/codec_ceiling.py`` share them):

- :mod:`iwsim.yardstick.fidelity`: open loop on held-out episodes (one-step and open-loop
  errors, the action gap, PSNR, the pushers and the block the frames show);
- :mod:`iwsim.yardstick.studies`: the studies' quick checks (the datagen study's
  teleoperation of a model, frame strips of one episode in each model and in MuJoCo);
- :mod:`iwsim.yardstick.codec`: the codec's ceiling on success frames;
- :mod:`iwsim.yardstick.families`: operator families held out of training, the idle
  measure and contact-then-rest.

They sit above the studies (they run the studies' evaluations and teleoperation) and, where
they read T-push's objects off the frames, are ground-truth tooling
(``iwsim.core.layers.GROUND_TRUTH_TOOLING``).
"""
