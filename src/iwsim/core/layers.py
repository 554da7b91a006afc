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
    # 1. foundations (core/: errors, resources, the numeric path, checkpoints and saved run
    #    state, metrics, configs, the one-writer lock, the generic training loop), network
    #    blocks, noise schedules and samplers
    ("iwsim.core", "iwsim.models", "iwsim.diffusion"),
    # 2. data: the episode store, frames for the models, the formats policy libraries read
    ("iwsim.data",),
    # 3. the tasks: MuJoCo ground truth, scripted policies, pixel scorers, the Task seam and
    #    registry, collection into a store
    ("iwsim.envs",),
    # 4. the models as objects, each with its training: the world model (codecs, dynamics,
    #    its Gymnasium envs) and the policies
    ("iwsim.world_model", "iwsim.policies"),
    # 5. what uses them: evaluation (with iwsim bench and iwsim demo), play
    ("iwsim.eval", "iwsim.play"),
    # 6. the studies; 7. the yardstick's measures (a model against MuJoCo, over the studies'
    #    machinery); 8. the command line
    ("iwsim.experiments",),
    ("iwsim.yardstick",),
    ("iwsim.cli", "iwsim.commands"),
]


# A task's own modules: its ground truth (simulator, geometry, pixel scorer, scripted
# policies) and its Task class, and what the tabletop tasks share (the tabletop's scene and
# control, its colour model, scripting, its Task base). Everything else reaches a task
# through the Task seam (iwsim.envs.task, the registry iwsim.envs.registry), so a world
# model of any robot runs through the same code (tests/test_layers.py checks it).
TASK_MODULES = ("iwsim.envs.pusht", "iwsim.envs.pilesweep", "iwsim.envs.tabletop")
TASK_IMPORTERS = ("iwsim.envs",)  # envs/ itself: the tasks, their registry and collection
# The ground-truth tooling, by name: it runs a MuJoCo simulator or its scripted policies,
# which no other robot's data comes with.
GROUND_TRUTH_TOOLING = {
    "iwsim.policies.scripted": "the tasks' scripted policies behind the policy interface, degraded as the tabletop's "
                               "(iwsim.envs.tabletop.scripting.Degraded)",
    "iwsim.eval.profiling": "the yardstick's measures of T-push's objects (block pose, pushers)",
    "iwsim.yardstick.families": "the idle and contact-then-rest measures fit T-push's block in MuJoCo's frames and the "
                                "model's (estimate_block_pose, the view's size)",
    "iwsim.yardstick.fidelity": "open-loop fidelity reads T-push's pushers and block off the decoded frames "
                                "(pusher_peaks, estimate_block_pose, the view's size)",
    "iwsim.yardstick.codec": "the codec's ceiling scores frames with T-push's pixel IoU",
}

# T-push's defaults (frame size, evaluation horizon, shipped checkpoint) live on its Task
# (iwsim.envs.pusht.task.PushTTask, the commands' iwsim.envs.registry.DEFAULT_TASK, the studies'
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
