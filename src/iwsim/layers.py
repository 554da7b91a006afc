"""The package's layers, bottom to top: a module imports only from its own layer or the
layers below it, and no imports form a cycle (``tests/test_layers.py`` checks both).

A name stands for a module or a package and everything in it; a module belongs to the
longest name that covers it. The package's ``__init__`` (``import iwsim``: the Gymnasium
ids, ``__version__`` and a lazy ``iwsim.WorldModel``) is outside the layers: the one
import that reaches up, on purpose. ``iwsim.WorldModel.load(path)`` is public, and only a
lazy attribute gives it without importing torch on ``import iwsim`` (the command line and
collection's workers import the package); ``tests/test_layers.py`` checks it stays the only
one.
"""

LAYERS: list[tuple[str, ...]] = [
    # 1. foundations: network blocks, noise and samplers, checkpoint I/O, metrics, errors,
    #    configs, the numeric path (bf16 where the CPU has it), the one-writer lock (of stores
    #    and run directories), the generic training loop
    ("iwsim.errors", "iwsim.resources", "iwsim.precision", "iwsim.models", "iwsim.diffusion", "iwsim.checkpoint",
     "iwsim.metrics", "iwsim.normalize", "iwsim.config", "iwsim.layers", "iwsim.data.lock", "iwsim.training.trainer",
     "iwsim.training.distributed"),
    # 2. the ground truth: MuJoCo tasks, their scripted policies, pixel scorers
    ("iwsim.envs",),
    # 3. data and the task registry; collection, a tool over the registry's tasks (it lives
    #    beside the store in data/ but sits above the registry); then the models as objects
    #    (the world model with its codecs and its training)
    ("iwsim.data", "iwsim.tasks"),
    ("iwsim.data.collect",),
    ("iwsim.world_model", "iwsim.policies"),
    # 4. Gymnasium envs over a world model
    ("iwsim.world_model_env",),
    # 5. what uses all of it (policy training, evaluation, play), the studies, the yardstick's
    #    measures (a model against MuJoCo, over the studies' machinery), then the command line
    ("iwsim.training", "iwsim.eval", "iwsim.play", "iwsim.demo"),
    ("iwsim.experiments",),
    ("iwsim.yardstick",),
    ("iwsim.cli", "iwsim.commands"),
]


# A task's own modules: its ground truth (simulator, geometry, pixel scorer, scripted
# policies) and its Task class, and what the tabletop tasks share (the tabletop's scene and
# control, its colour model, scripting, its Task base). Everything else reaches a task
# through the Task seam (iwsim.envs.task, the registry iwsim.tasks), so a world model of any
# robot runs through the same code (tests/test_layers.py checks it).
TASK_MODULES = ("iwsim.envs.pusht", "iwsim.envs.pixels", "iwsim.envs.geometry", "iwsim.envs.scripted",
                "iwsim.envs.pusht_task",
                "iwsim.envs.pilesweep", "iwsim.envs.pilesweep_pixels", "iwsim.envs.pilesweep_scripted",
                "iwsim.envs.pilesweep_task",
                "iwsim.envs.tabletop", "iwsim.envs.palette", "iwsim.envs.scripting", "iwsim.envs.tabletop_task")
TASK_IMPORTERS = ("iwsim.envs", "iwsim.tasks")  # envs/ itself and the Task registry
# The ground-truth tooling, by name: it runs a MuJoCo simulator or its scripted policies,
# which no other robot's data comes with.
GROUND_TRUTH_TOOLING = {
    "iwsim.policies.scripted": "the tasks' scripted policies behind the policy interface, degraded as the tabletop's "
                               "(iwsim.envs.scripting.Degraded)",
    "iwsim.eval.profiling": "the yardstick's measures of T-push's objects (block pose, pushers)",
    "iwsim.yardstick.families": "the idle and contact-then-rest measures fit T-push's block in MuJoCo's frames and the "
                                "model's (estimate_block_pose, the view's size)",
    "iwsim.yardstick.fidelity": "open-loop fidelity reads T-push's pushers and block off the decoded frames "
                                "(pusher_peaks, estimate_block_pose, the view's size)",
    "iwsim.yardstick.codec": "the codec's ceiling scores frames with T-push's pixel IoU",
}

# T-push's defaults (frame size, evaluation horizon, shipped checkpoint) live on its Task
# (iwsim.envs.pusht_task.PushTTask, the commands' iwsim.tasks.DEFAULT_TASK, the studies'
# iwsim.experiments.common.STUDY). Modules that still spell one out (the shipped checkpoint's
# path, or a module-level get_task("pusht")), each with why; tests/test_layers.py checks
# that no other module does and that the list only shrinks, and that outside T-push's modules,
# the registry and the presets no frame size defaults to 64 pixels nor a task to "pusht".
T_PUSH_DEFAULTS_SPELLED: dict[str, str] = {}


def within(module: str, names: tuple[str, ...] | dict) -> bool:
    """Whether ``module`` is one of ``names`` or inside one of them."""
    return any(module == n or module.startswith(n + ".") for n in names)


def layer_of(module: str) -> int | None:
    """The index in :data:`LAYERS` of ``module`` (a dotted name), or None if no layer holds it."""
    best: tuple[int, int] | None = None  # (length of the matching name, layer)
    for i, names in enumerate(LAYERS):
        for name in names:
            if (module == name or module.startswith(name + ".")) and (best is None or len(name) > best[0]):
                best = (len(name), i)
    return None if best is None else best[1]
