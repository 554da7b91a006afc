"""Networks only: encoder, decoder and dynamics. Noise logic lives in ``iwsim.diffusion``."""
