"""The paper's two robot-learning studies, one command each (``iwsim experiment``):

- :mod:`iwsim.experiments.datagen`: policies trained on demonstrations generated inside
  the world model against policies trained on simulator demonstrations;
- :mod:`iwsim.experiments.policy_eval`: whether a policy's score inside the world model
  ranks policies as the simulator does.
"""
