"""Noise schedules, diffusion losses and samplers: pure functions over any network.

One calling convention, in the style of k-diffusion. A network is wrapped once by the
module of its parameterisation (:class:`~iwsim.diffusion.consistency.JumpModel`,
:class:`~iwsim.diffusion.edm.Denoiser`, :class:`~iwsim.diffusion.ddpm.EpsDenoiser`); the
wrapped model is called

    model(x, t, s, **extra_args)

with ``x`` (B, ...) at level ``t`` (B,) and ``s`` (B,) the level the sampler moves it to;
it returns its estimate of the sample at ``s`` (a consistency jump) or of the clean
sample (the denoisers, which ignore ``s``). ``extra_args`` (the condition) are passed
through untouched to the inner network, which is called ``net(x, t, s, **extra_args)``
(the DDPM noise predictor: ``net(x, t, **extra_args)``). Every sampler is a plain function

    sample_<name>(model, x, levels, extra_args=None) -> Tensor

from ``x`` at ``levels[0]`` down the list of levels to the last one, and every wrapper
has a ``loss`` for its training objective.
"""
