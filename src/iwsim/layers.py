"""The package's layers, bottom to top: a module imports only from its own layer or the
layers below it, and no imports form a cycle (``tests/test_layers.py`` checks both).

A name stands for a module or a package and everything in it; a module belongs to the
longest name that covers it. The package's ``__init__`` (``import iwsim``: the Gymnasium
ids, ``__version__`` and a lazy ``iwsim.WorldModel``) is outside the layers.
"""

LAYERS: list[tuple[str, ...]] = [
    # 1. foundations: network blocks, noise and samplers, checkpoint I/O, metrics, errors,
    #    configs, the generic training loop
    ("iwsim.errors", "iwsim.resources", "iwsim.models", "iwsim.diffusion", "iwsim.checkpoint", "iwsim.metrics",
     "iwsim.normalize", "iwsim.config", "iwsim.layers", "iwsim.training.trainer", "iwsim.training.distributed"),
    # 2. the ground truth: MuJoCo tasks, their scripted policies, pixel scorers
    ("iwsim.envs",),
    # 3. data and the task registry, then the models as objects (the world model with its codecs and its training)
    ("iwsim.data", "iwsim.tasks"),
    ("iwsim.world_model", "iwsim.policies"),
    # 4. Gymnasium envs over a world model
    ("iwsim.world_model_env",),
    # 5. what uses all of it (policy training, evaluation, play), the studies, then the command line
    ("iwsim.training", "iwsim.eval", "iwsim.play", "iwsim.demo"),
    ("iwsim.experiments",),
    ("iwsim.cli",),
]


def layer_of(module: str) -> int | None:
    """The index in :data:`LAYERS` of ``module`` (a dotted name), or None if no layer holds it."""
    best: tuple[int, int] | None = None  # (length of the matching name, layer)
    for i, names in enumerate(LAYERS):
        for name in names:
            if (module == name or module.startswith(name + ".")) and (best is None or len(name) > best[0]):
                best = (len(name), i)
    return None if best is None else best[1]
