"""iwsim play end to end in a real browser: Debian's chromium driven by Playwright against
the real server (a tiny world model): keys, mouse drag, record, save, discard, side by side;
pile sweeping (a second MuJoCo task) driven, recorded and beside its simulator;
and for tasks other than T-push (the point task of ``conftest.point_model``, 14-D actions)
the task's key bindings and a slider per action dimension."""

import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from iwsim.data.store import EpisodeStore
from iwsim.play.server import running
from tests.test_play import engine

pytestmark = pytest.mark.browser

CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
         "--no-first-run"]


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing; `make test` installs Debian's chromium package.")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS, headless=True)
        yield b
        b.close()


@contextmanager
def served_page(browser, eng, height: int = 900, init_script: str | None = None):
    """``eng`` served (:func:`running`) and its page open in ``browser`` (1500 x ``height``,
    the token in its address) once the first frames have arrived; the test fails on any
    error the page raised."""
    errors: list[str] = []
    with running(eng) as srv:
        page = browser.new_page(viewport={"width": 1500, "height": height})
        page.on("pageerror", lambda e: errors.append(str(e)))
        if init_script:
            page.add_init_script(init_script)
        page.goto(srv.page)
        wait(page, "window.iwsim.stats.frames > 2")
        yield page
        page.close()
    assert not errors, errors


def wait(page, js: str, timeout: float = 15.0) -> None:
    page.wait_for_function(js, timeout=timeout * 1000)


def target(page) -> np.ndarray:
    return np.array(page.evaluate("window.iwsim.state.target"))


def room(v: float) -> float:
    """+1 or -1: the direction with more room to move a target coordinate (starts are random,
    and a target at the workspace edge cannot move further out)."""
    return 1.0 if v <= 0 else -1.0


def settle(page) -> None:
    """Wait until the page has sent its latest command (continuous motion is sent at most
    twice per control step, so the last change may still be waiting) and a frame has
    acknowledged it."""
    wait(page, "(() => { const s = window.iwsim.state;"
               " return s.sent && s.target.every((v, i) => v === s.sent[i]) && s.header.ack >= s.seq; })()")


def hold_d_or_a(page) -> tuple[np.ndarray, np.ndarray, float]:
    """Hold D (or A, whichever way the first dimension has room) for 0.4 s: the command
    before and after, and the direction (+1 for D)."""
    before = target(page)
    sx = room(before[0])
    key = "d" if sx > 0 else "a"
    page.keyboard.down(key)
    time.sleep(0.4)
    page.keyboard.up(key)
    settle(page)
    return before, target(page), sx


# A stand-in for the browser's Gamepad API: tests set window.fakePad.axes / .buttons.
FAKE_PAD = """
window.fakePad = {index: 0, id: "fake pad", axes: [0, 0, 0, 0],
                  buttons: Array.from({length: 17}, () => ({pressed: false, value: 0}))};
navigator.getGamepads = () => [window.fakePad];
"""


def test_gamepad_sticks_and_buttons(browser):
    with served_page(browser, engine(hz=20), init_script=FAKE_PAD) as page:
        before = target(page)
        sx, sy = room(before[0]), room(before[3])  # left stick along x, right stick along y (up is -)
        page.evaluate(f"window.fakePad.axes = [{0.9 * sx}, 0, 0, {-0.9 * sy}]")
        time.sleep(0.4)
        page.evaluate("window.fakePad.axes = [0, 0, 0, 0]")
        settle(page)
        after = target(page)
        assert sx * (after[0] - before[0]) > 0.02 and sy * (after[3] - before[3]) > 0.02
        assert np.allclose(after[[1, 2]], before[[1, 2]])
        page.evaluate("window.fakePad.buttons[2].pressed = true")  # X: record
        wait(page, "document.getElementById('message').textContent.includes('recording is off')")


def test_drive_record_and_save_in_chromium(browser, tmp_path):
    store = tmp_path / "demos.zarr"
    eng = engine(record_to=store, hz=20)
    with served_page(browser, eng) as page:
        assert page.inner_text("#conn") == "connected"
        canvas = page.eval_on_selector("#wm", "c => c.toDataURL()")

        # keys: D (A) moves the left pusher's target right (left), and the frames follow
        before, after, sx = hold_d_or_a(page)
        assert sx * (after[0] - before[0]) > 0.02 and np.allclose(after[1:], before[1:])
        assert page.eval_on_selector("#wm", "c => c.toDataURL()") != canvas
        assert np.allclose(page.evaluate("window.iwsim.state.header.action"), after, atol=1e-6)
        assert page.evaluate("window.iwsim.stats.latencyLast") > 0
        assert "ms" in page.inner_text("#latency") and float(page.inner_text("#fps")) > 0

        # mouse: drag the right pusher's ring towards the centre
        box = page.locator("#wm").bounding_box()
        vh = page.evaluate("window.iwsim.state.hello.view_half")
        before = target(page)

        def on_page(x: float, y: float) -> tuple[float, float]:
            return box["x"] + (x + vh) / (2 * vh) * box["width"], box["y"] + (vh - y) / (2 * vh) * box["height"]

        page.mouse.move(*on_page(before[2], before[3]))
        page.mouse.down()
        page.mouse.move(*on_page(0.0, 0.0), steps=5)
        time.sleep(0.5)
        page.mouse.up()
        settle(page)
        after = target(page)
        assert np.hypot(*after[2:]) < np.hypot(*before[2:]) - 0.02 or np.hypot(*after[2:]) < 0.01
        assert np.allclose(after[:2], before[:2])

        # record (c), move the right pusher up (i), save (Shift+S)
        page.keyboard.press("c")
        wait(page, "document.getElementById('rec').textContent.includes('REC')")
        page.keyboard.down("i")
        time.sleep(0.5)
        page.keyboard.up("i")
        wait(page, "window.iwsim.state.header.recording >= 5")
        page.keyboard.press("Shift+S")
        wait(page, "document.getElementById('message').textContent.includes('saved episode 0')")
        assert page.inner_text("#rec") == ""

        # record and discard with the buttons
        page.click("#record")
        wait(page, "window.iwsim.state.header.recording >= 2")
        page.click("#discard")
        wait(page, "document.getElementById('message').textContent.includes('discarded')")

        # side by side shows MuJoCo next to the model
        assert page.locator("#twin-view").is_hidden()
        page.click("#side")
        wait(page, "!document.getElementById('twin-view').hidden")
        wait(page, "window.iwsim.state.header.mujoco_iou !== null")

    back = EpisodeStore.open(store)
    assert back.n_episodes == 1
    ep = back.episode(0)
    assert len(ep["img"]) >= 5 and ep["img"].dtype == np.uint8 and ep["img"].shape[1:] == (64, 64, 3)
    right_y = ep["action"][:, 3]
    assert right_y[-1] > right_y[0] + 0.02  # i moved the right pusher up while recording
    assert np.allclose(ep["action"][:, :3], ep["action"][0, :3])


def recording_engine(checkpoint: Path, store: Path):
    """The play engine of a world-model checkpoint, recording into ``store``, at 20 Hz."""
    from iwsim.play.engine import Engine, PlayConfig
    from iwsim.world_model import WorldModel

    return Engine(WorldModel.load(checkpoint), PlayConfig(record_to=store, hz=20))


def test_pile_sweeping_driven_recorded_and_side_by_side_in_chromium(browser, pile_model, tmp_path):
    """The second MuJoCo task in the browser: the same bindings drive the pushers, a take is
    recorded with the task's score, and side by side shows its simulator and score."""
    store = tmp_path / "pile_demos.zarr"
    eng = recording_engine(pile_model["checkpoint"], store)
    with served_page(browser, eng) as page:
        before, after, sx = hold_d_or_a(page)
        assert sx * (after[0] - before[0]) > 0.02 and np.allclose(after[1:], before[1:])
        page.keyboard.press("c")
        wait(page, "document.getElementById('rec').textContent.includes('REC')")
        wait(page, "window.iwsim.state.header.recording >= 5")
        page.keyboard.press("Shift+S")
        wait(page, "document.getElementById('message').textContent.includes('saved episode 0')")
        page.click("#side")
        wait(page, "!document.getElementById('twin-view').hidden")
        wait(page, "window.iwsim.state.header.mujoco_iou !== null")
    ep = EpisodeStore.open(store).episode(0)
    assert len(ep["img"]) >= 5 and ep["img"].shape[1:] == (64, 64, 3)
    assert ((ep["score"] >= 0) & (ep["score"] <= 1)).all()


# -- a task other than T-push: keys and sliders from the task's bindings ------------------------


def wide_world_model(store: Path, action_dim: int = 14):
    """A tiny random world model with ALOHA-sized actions, whose generic task starts from ``store``."""
    import dataclasses

    import torch

    from iwsim.envs.registry import task_from_store
    from iwsim.world_model import WorldModel
    from iwsim.world_model.codecs.consistency import Autoencoder
    from iwsim.world_model.dynamics import Dynamics
    from iwsim.world_model.presets import AE_PRESETS
    from tests.test_dynamics import randomise, tiny_cfg

    cfg = tiny_cfg()
    cfg = dataclasses.replace(cfg, dynamics=dataclasses.replace(cfg.dynamics, action_dim=action_dim, point_index=(),
                                                                point_scale=(), point_offset=()))
    torch.manual_seed(0)
    wm = WorldModel(Autoencoder(AE_PRESETS["tiny"]), randomise(Dynamics(cfg.dynamics)), cfg,
                    [-1.0] * action_dim, [1.0] * action_dim).eval()
    wm.task = task_from_store(store, wm.action_low.tolist(), wm.action_high.tolist())
    return wm


def test_point_task_driven_with_keys_gamepad_and_sliders_and_recorded(browser, point_model, tmp_path):
    demos = tmp_path / "demos.zarr"
    eng = recording_engine(point_model["checkpoint"], demos)
    with served_page(browser, eng, init_script=FAKE_PAD) as page:
        sliders = page.locator("#sliders input[type=range]")
        assert sliders.count() == 2 and page.locator("#sliders span").all_inner_texts() == ["x", "y"]
        assert page.inner_text("#iou") == "no scorer" and page.locator("#side-row").is_hidden()
        assert page.inner_text("#reset-mujoco").startswith("Dataset start")

        # a key (D / A) moves x by the task's step per control step, y stays
        before, after, sx = hold_d_or_a(page)
        assert sx * (after[0] - before[0]) > 0.02 and after[1] == before[1]
        assert np.allclose(page.evaluate("window.iwsim.state.header.action"), after, atol=1e-6)
        assert float(page.inner_text("#sliders output >> nth=0")) == pytest.approx(after[0], abs=1e-3)

        # gamepad axis 1 (a stick's up is negative) moves y, x stays
        before = target(page)
        sy = room(before[1])
        page.evaluate(f"window.fakePad.axes = [0, {-0.9 * sy}, 0, 0]")
        time.sleep(0.4)
        page.evaluate("window.fakePad.axes = [0, 0, 0, 0]")
        settle(page)
        after = target(page)
        assert sy * (after[1] - before[1]) > 0.02 and after[0] == before[0]

        # the y slider sets y; the frames follow
        page.keyboard.press("c")
        wait(page, "document.getElementById('rec').textContent.includes('REC')")
        sliders.nth(1).fill("0.25")
        settle(page)
        assert target(page)[1] == pytest.approx(0.25, abs=1e-3)
        assert page.evaluate("window.iwsim.state.header.action")[1] == pytest.approx(0.25, abs=1e-3)
        wait(page, "window.iwsim.state.header.recording >= 4")
        page.keyboard.press("Shift+S")
        wait(page, "document.getElementById('message').textContent.includes('saved episode 0')")
    ep = EpisodeStore.open(demos).episode(0)
    assert sorted(ep) == ["action", "img", "state", "target"] and ep["action"].shape[1] == 2
    assert ep["action"][-1, 1] == pytest.approx(0.25, abs=1e-3)


def test_fourteen_dimensions_get_fourteen_sliders(browser, tmp_path):
    """ALOHA-sized actions: a slider per dimension, each moving only its own dimension."""
    store = EpisodeStore.create(tmp_path / "aloha.zarr", {"task": "aloha-like", "fps": 50, "image_size": 64})
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.5, 0.5, (6, 14)).astype(np.float32)
    store.append({"img": rng.integers(0, 256, (6, 64, 64, 3), dtype=np.uint8), "action": actions})
    from iwsim.play.engine import Engine, PlayConfig

    eng = Engine(wide_world_model(tmp_path / "aloha.zarr"), PlayConfig(hz=20))
    with served_page(browser, eng, height=1400) as page:
        sliders = page.locator("#sliders input[type=range]")
        assert sliders.count() == 14
        np.testing.assert_allclose(target(page), actions[0], atol=1e-6)  # the episode's first command
        sliders.nth(13).fill("0.75")
        settle(page)
        want = actions[0].copy()
        want[13] = 0.75
        np.testing.assert_allclose(target(page), want, atol=1e-3)
        np.testing.assert_allclose(page.evaluate("window.iwsim.state.header.action"), want, atol=1e-3)
